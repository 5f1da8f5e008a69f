"""A driver's whole contract is in drivers/base.py, and every backend keeps it: the methods the
protocols name exist on each implementation and take the parameters the protocol names, so a
caller written against the protocol cannot meet a backend that lacks a method or renames an
argument. The backends a config may name are the ones the device opener knows."""

from __future__ import annotations

import inspect
import typing

import pytest
from rig.drivers.base import BusSlider, LoadCell, Slider
from rig.drivers.modbus_slider import ModbusSlider
from rig.drivers.serial_loadcell import SerialLoadCell
from rig.sim.inprocess import InProcessLoadCell, InProcessSlider

from rig.control import devices
from rig.specs.config import LoadCellConfig, SliderConfig

CASES = [(Slider, ModbusSlider), (Slider, InProcessSlider), (BusSlider, ModbusSlider),
         (LoadCell, SerialLoadCell), (LoadCell, InProcessLoadCell)]


def _methods(protocol) -> dict[str, inspect.Signature]:
    out = {}
    for klass in protocol.__mro__:
        if klass in (typing.Protocol, typing.Generic, object):
            continue
        for name, member in vars(klass).items():
            if inspect.isfunction(member) and not name.startswith("_"):
                out.setdefault(name, inspect.signature(member))
    return out


@pytest.mark.parametrize(("protocol", "impl"), CASES, ids=lambda c: c.__name__)
def test_every_backend_keeps_its_protocol(protocol, impl):
    methods = _methods(protocol)
    assert methods, protocol
    for name, wanted in methods.items():
        assert hasattr(impl, name), f"{impl.__name__} lacks {protocol.__name__}.{name}"
        got = inspect.signature(getattr(impl, name))
        params = [p for p in wanted.parameters.values() if p.name != "self"]
        have = got.parameters
        for p in params:
            assert p.name in have, f"{impl.__name__}.{name} has no parameter {p.name!r}"
            if p.default is not inspect.Parameter.empty:
                assert have[p.name].default is not inspect.Parameter.empty, \
                    f"{impl.__name__}.{name}: {p.name!r} is optional in the protocol, required here"
        required = [n for n, q in have.items() if n != "self" and q.default is inspect.Parameter.empty
                    and q.kind not in (q.VAR_POSITIONAL, q.VAR_KEYWORD)]
        assert set(required) <= {p.name for p in params}, \
            f"{impl.__name__}.{name} requires {set(required) - {p.name for p in params}}, beyond its protocol"


def _choices(cls, name: str) -> set[str]:
    return set(next(f for f in cls.__dataclass_fields__.values() if f.name == name).metadata["choices"])


def test_the_config_names_only_backends_the_opener_knows():
    assert _choices(SliderConfig, "backend") == {*devices.SLIDERS, devices.SIMULATED}
    assert _choices(LoadCellConfig, "backend") == {*devices.LOADCELLS, devices.SIMULATED, devices.NO_LOADCELL}


def test_devices_close_however_the_block_ends(monkeypatch):
    from rig.clock import VirtualClock
    from rig.specs.config import RigConfig

    closed = []
    with pytest.raises(RuntimeError), devices.open_devices(RigConfig(), VirtualClock()) as dev:
        monkeypatch.setattr(dev.slider, "close", lambda: closed.append("slider"))
        monkeypatch.setattr(dev.loadcell, "close", lambda: closed.append("loadcell"))
        raise RuntimeError("a failure inside the block")
    assert closed == ["slider", "loadcell"]
