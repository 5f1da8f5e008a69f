"""An effect is declared by keyword and checked when it is: its function takes the stage's
inputs, then exactly its parameters by name. A misspelt parameter fails at the declaration (and
in a plugin file, at its line), not deep inside the first fit."""

from __future__ import annotations

import pytest

from rig.errors import RigError
from rig.models.catalogue import CATALOGUE
from rig.models.core import STAGE_INPUTS, Effect, Param
from rig.models.plugins import load_plugin


def _viscous(x, v, eta_N_s_per_m):
    return eta_N_s_per_m * v


def test_a_declared_effect_names_what_it_takes():
    e = Effect(name="viscous_again", stage="drive", fn=_viscous, equation="eta v", signature="-",
               params=(Param("eta_N_s_per_m", "N s/m", 0.1),))
    assert e.params[0].name == "eta_N_s_per_m"


def test_a_misspelt_parameter_fails_at_the_declaration():
    with pytest.raises(ValueError, match=r"its parameters are eta_Ns_per_m, but its function takes "
                                         r"eta_N_s_per_m after the inputs \(x, v\)"):
        Effect(name="viscous_again", stage="drive", fn=_viscous, equation="eta v", signature="-",
               params=(Param("eta_Ns_per_m", "N s/m", 0.1),))


def test_a_function_for_another_stage_fails_at_the_declaration():
    # a sensor term takes (m, force): this one takes (x, v), so eta would be given as the force
    with pytest.raises(ValueError, match="sensor stage"):
        Effect(name="viscous_again", stage="sensor", fn=lambda m, eta_N_s_per_m: 0.0, equation="-",
               signature="-", params=(Param("eta_N_s_per_m", "N s/m", 0.1),))


def test_positional_declarations_are_refused():
    with pytest.raises(TypeError):
        Effect("viscous_again", "drive", (Param("eta_N_s_per_m", "N s/m", 0.1),), _viscous, "eta v", "-")


def test_every_catalogue_effect_keeps_its_stage_inputs():
    assert set(STAGE_INPUTS) >= {e.stage for e in CATALOGUE.values()}
    assert len(CATALOGUE) >= 15  # all of them were declared (each checked as it was)


def test_a_plugin_with_a_misspelt_parameter_is_refused_at_its_line(tmp_path):
    path = tmp_path / "mine.py"
    path.write_text("from rig.models import Param, effect\n\n"
                    "@effect(stage='drive', params=[Param('k_N_per_m', 'N/m', 1.0)])\n"
                    "def stiff(x, v, k_N_per_mm):\n"
                    "    return k_N_per_mm * x\n")
    with pytest.raises(RigError, match=r"mine\.py:3: ValueError: effect 'stiff' \(drive stage\): its "
                                       r"parameters are k_N_per_m, but its function takes k_N_per_mm"):
        load_plugin(path)
