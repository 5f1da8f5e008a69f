"""nanite's serial loop over the first N curves of a force map, as its users run it (preprocessing,
hertz_para at R = 5 um, weight_cp=0), in its own process: prints the curves per second last.
A benchmark-only peer (GPL), run only from tests/bench/test_bench_map.py.

    python tests/bench/nanite_map_loop.py MAP.h5 N
"""

import sys
import time
import warnings

import nanite
import nanite.fit

warnings.filterwarnings("ignore")

path, n = sys.argv[1], int(sys.argv[2])
PRE = ["compute_tip_position", "correct_force_offset", "correct_tip_offset", "correct_split_approach_retract"]
t0 = time.perf_counter()
group = nanite.IndentationGroup(path)
t1 = time.perf_counter()
done = 0
for idnt in list(group)[:n]:
    idnt.apply_preprocessing(PRE)
    params = idnt.get_initial_fit_parameters(model_key="hertz_para")
    params["R"].value = 5e-6
    params["nu"].value = 0.5
    idnt.fit_model(model_key="hertz_para", params_initial=params, segment="approach", weight_cp=0)
    done += 1
t2 = time.perf_counter()
print(f"nanite: load {t1 - t0:.2f} s, {done} curves fitted in {t2 - t1:.2f} s; curves/s, load included: "
      f"{done / (t2 - t0):.3f}")
