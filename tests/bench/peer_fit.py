"""The peer: the paper's model fitted to one trial CSV with plain scipy, as a researcher would
write it (read, differentiate, fit f + tau1 f' = k1 x^3 + k2 x^2 + k3 x + tau2 x x', print).

    python tests/bench/peer_fit.py trial.csv
"""

import sys

import numpy as np
from scipy.optimize import least_squares
from scipy.signal import lfilter, savgol_filter

data = np.genfromtxt(sys.argv[1], delimiter=",", names=True)
t, x, f = data["t_s"], data["position_mm"] / 1000.0, data["force_N"]
dt = float(np.median(np.diff(t)))
v = savgol_filter(x, 15, 2, deriv=1, delta=dt)
contact = x > 0
xc, vc = np.where(contact, x, 0.0), np.where(contact, v, 0.0)
scale = np.array([5e4, 500.0, 20.0, 1e5, 5.0])


def model(p):
    k1, k2, k3, tau2, tau1 = p * scale
    drive = np.where(contact, ((k1 * xc + k2) * xc + k3) * xc + tau2 * xc * vc, 0.0)
    a = np.exp(-dt / tau1)
    return np.maximum(lfilter([1 - a], [1, -a], drive), 0.0)


sol = least_squares(lambda p: model(p) - f, np.ones(5), bounds=([-np.inf] * 4 + [0.002], np.inf),
                    method="trf", ftol=1e-10, xtol=1e-10, gtol=1e-10)
r = f - model(sol.x)
names = ["k1_N_per_m3", "k2_N_per_m2", "k3_N_per_m", "tau2_N_s_per_m2", "tau1_s"]
for n, val in zip(names, sol.x * scale, strict=True):
    print(f"{n:<16} {val:12.5g}")
print(f"RMSE {np.sqrt(np.mean(r ** 2)):.4f} N, noise {np.std(np.diff(r)) / np.sqrt(2):.4f} N")
