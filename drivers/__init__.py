"""Hardware drivers: the slider (Modbus) and the load cell (serial), behind `rig.drivers.base`."""
