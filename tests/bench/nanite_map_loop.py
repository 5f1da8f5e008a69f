"""nanite's serial loop over the first N curves of a force map, or of a folder's files, as its users
run it (each file opened as an IndentationGroup, preprocessing, hertz_para at R = 5 um,
weight_cp=0), in its own process: prints the curves per second last. A benchmark-only peer (GPL),
run only from tests/bench/test_bench_map.py and tests/bench/test_bench_folder.py.

    python tests/bench/nanite_map_loop.py MAP.h5 N
    python tests/bench/nanite_map_loop.py FILE... N
"""

import sys
import time
import warnings
from itertools import islice

import nanite
import nanite.fit

warnings.filterwarnings("ignore")

*paths, n = sys.argv[1:]
PRE = ["compute_tip_position", "correct_force_offset", "correct_tip_offset", "correct_split_approach_retract"]
t0 = time.perf_counter()
groups = [nanite.IndentationGroup(path) for path in paths]
t1 = time.perf_counter()
done = 0
for idnt in islice((idnt for group in groups for idnt in group), int(n)):
    idnt.apply_preprocessing(PRE)
    params = idnt.get_initial_fit_parameters(model_key="hertz_para")
    params["R"].value = 5e-6
    params["nu"].value = 0.5
    idnt.fit_model(model_key="hertz_para", params_initial=params, segment="approach", weight_cp=0)
    done += 1
t2 = time.perf_counter()
print(f"nanite: load {t1 - t0:.2f} s, {done} curves fitted in {t2 - t1:.2f} s; curves/s, load included: "
      f"{done / (t2 - t0):.3f}")
