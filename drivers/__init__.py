"""Hardware drivers: the slider (Modbus) and the load cell (serial), behind `drivers.base`."""
