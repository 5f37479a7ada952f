#!/usr/bin/env python3
"""Reference corrections (scikit-learn SVR, scipy LM-trained 3-H-3 MLP) to set
beside the Rust learners (`spidar::learn`).

Usage (needs `pip install scikit-learn numpy scipy`; never run by CI):

    python3 scripts/reference/reference.py TRAIN.csv TEST.csv \\
        [--mode absolute|residual] [--hidden 20] [--restarts 2] \\
        [--max-nfev 400] [--grid paper|wide|none] [--seed 1]

TRAIN.csv and TEST.csv hold one pair per row with a header line:
`x,y,z,tx,ty,tz`, the device position (input) and the tracker position
(target), in mm. `cargo run --release -p spidar --example learn_bench --
--csv DIR` writes such files for the synthetic field.

What it does, mirroring the Rust side:
- standardization (paper eq. 10) with the population std (numpy's and
  StandardScaler's default, as `spidar::learn::standardize`), statistics over
  all training points;
- `--mode residual` learns target - input instead of the target;
- SVR: one RBF epsilon-SVR per axis (libsvm via scikit-learn, tol 1e-3,
  shrinking). With `--grid`, C/epsilon/gamma are chosen on a seeded 20 %
  hold-out of the training set by mean position error, then refit on all of
  it; `--grid none` uses C=100, epsilon=0.01, gamma=1/3;
- MLP: y = W2 tanh(W1 x + b1) + b2 trained by scipy.optimize.least_squares
  (method='lm', MINPACK) with an analytic Jacobian, `--restarts` Nguyen-Widrow
  style random initializations, best on a seeded 15 % validation split.

It prints one JSON object: raw, svr and nn test statistics (mean, sd with
n - 1, max of the Euclidean position error in mm), the chosen SVR parameters,
and the seconds each fit took.
"""
import argparse
import csv
import json
import time

import numpy as np
from scipy.optimize import least_squares
from sklearn.svm import SVR


def load(path):
    with open(path) as f:
        rows = list(csv.reader(f))
    data = np.array([[float(v) for v in r] for r in rows[1:] if r])
    return data[:, :3], data[:, 3:6]


def stats(pred, truth):
    d = np.linalg.norm(pred - truth, axis=1)
    return {"mean": float(d.mean()), "sd": float(d.std(ddof=1)),
            "max": float(d.max()), "n": int(len(d))}


class Scaler:
    def __init__(self, a):
        self.mean = a.mean(axis=0)
        self.std = a.std(axis=0)  # population std, as the Rust side

    def fwd(self, a):
        return (a - self.mean) / self.std

    def inv(self, a):
        return a * self.std + self.mean


def targets_for(mode, x, t):
    return t - x if mode == "residual" else t


def positions_from(mode, x, y):
    return x + y if mode == "residual" else y


# ------------------------------------------------------------------ SVR --

GRIDS = {
    "paper": {"C": [30.0, 300.0], "epsilon": [0.01, 0.005], "gamma": [0.3, 1.0]},
    "wide": {"C": [10.0, 100.0, 1000.0], "epsilon": [0.02, 0.01, 0.005],
             "gamma": [0.1, 0.3, 1.0, 3.0]},
}


def fit_svr(xs, ys, c, eps, gamma):
    return [SVR(kernel="rbf", C=c, epsilon=eps, gamma=gamma, tol=1e-3,
                shrinking=True, cache_size=1000).fit(xs, ys[:, a]) for a in range(3)]


def predict_svr(models, xs):
    return np.stack([m.predict(xs) for m in models], axis=1)


def svr_reference(args, x, t, xt, tt):
    sx, sy = Scaler(x), Scaler(targets_for(args.mode, x, t))
    xs, ys = sx.fwd(x), sy.fwd(targets_for(args.mode, x, t))
    best = (100.0, 0.01, 1.0 / 3.0)
    t0 = time.time()
    searched = []
    if args.grid != "none":
        rng = np.random.default_rng(args.seed)
        idx = rng.permutation(len(x))
        nv = int(round(0.2 * len(x)))
        va, tr = idx[:nv], idx[nv:]
        best_err = np.inf
        g = GRIDS[args.grid]
        for gamma in g["gamma"]:
            for c in g["C"]:
                for eps in g["epsilon"]:
                    m = fit_svr(xs[tr], ys[tr], c, eps, gamma)
                    pred = positions_from(args.mode, x[va], sy.inv(predict_svr(m, xs[va])))
                    err = float(np.linalg.norm(pred - t[va], axis=1).mean())
                    searched.append({"C": c, "epsilon": eps, "gamma": gamma,
                                     "validation_mean_mm": err})
                    if err < best_err:
                        best_err, best = err, (c, eps, gamma)
    search_s = time.time() - t0
    t0 = time.time()
    models = fit_svr(xs, ys, *best)
    fit_s = time.time() - t0
    pred = positions_from(args.mode, xt, sy.inv(predict_svr(models, sx.fwd(xt))))
    return {"test": stats(pred, tt), "C": best[0], "epsilon": best[1], "gamma": best[2],
            "support_vectors": [int(len(m.support_)) for m in models],
            "search_seconds": search_s, "fit_seconds": fit_s, "candidates": searched}


# ------------------------------------------------------------------ MLP --

def unpack(w, h):
    w1 = w[:3 * h].reshape(h, 3)
    b1 = w[3 * h:4 * h]
    w2 = w[4 * h:7 * h].reshape(3, h)
    b2 = w[7 * h:7 * h + 3]
    return w1, b1, w2, b2


def forward(w, h, xs):
    w1, b1, w2, b2 = unpack(w, h)
    a = np.tanh(xs @ w1.T + b1)
    return a @ w2.T + b2, a


def residuals(w, h, xs, ys):
    f, _ = forward(w, h, xs)
    return (f - ys).T.ravel()  # output-major, as the Rust trainer


def jacobian(w, h, xs, ys):
    w1, b1, w2, b2 = unpack(w, h)
    n = len(xs)
    a = np.tanh(xs @ w1.T + b1)
    d = 1.0 - a * a
    jac = np.zeros((3 * n, 7 * h + 3))
    for k in range(3):
        rows = slice(k * n, (k + 1) * n)
        g = d * w2[k]  # n x h
        for i in range(3):
            jac[rows, i:3 * h:3] = g * xs[:, i:i + 1]
        jac[rows, 3 * h:4 * h] = g
        jac[rows, 4 * h + k * h:4 * h + (k + 1) * h] = a
        jac[rows, 7 * h + k] = 1.0
    return jac


def init_nw(h, xs, rng):
    beta = 0.7 * h ** (1.0 / 3.0)
    v = rng.standard_normal((h, 3))
    v *= beta / np.linalg.norm(v, axis=1, keepdims=True)
    b = rng.uniform(-beta, beta, h)
    lo, hi = xs.min(axis=0), xs.max(axis=0)
    s = 2.0 / np.maximum(hi - lo, 1e-9)
    o = -1.0 - s * lo
    w1 = v * s
    b1 = b + v @ o
    w2 = rng.uniform(-0.5, 0.5, (3, h))
    return np.concatenate([w1.ravel(), b1, w2.ravel(), np.zeros(3)])


def nn_reference(args, x, t, xt, tt):
    h = args.hidden
    sx, sy = Scaler(x), Scaler(targets_for(args.mode, x, t))
    xs, ys = sx.fwd(x), sy.fwd(targets_for(args.mode, x, t))
    rng = np.random.default_rng(args.seed)
    idx = rng.permutation(len(x))
    nv = int(round(0.15 * len(x)))
    va, tr = idx[:nv], idx[nv:]
    best, best_err = None, np.inf
    t0 = time.time()
    for _ in range(args.restarts):
        w0 = init_nw(h, xs[tr], rng)
        res = least_squares(residuals, w0, jac=jacobian, method="lm",
                            max_nfev=args.max_nfev, args=(h, xs[tr], ys[tr]))
        f, _ = forward(res.x, h, xs[va])
        pred = positions_from(args.mode, x[va], sy.inv(f))
        err = float(np.linalg.norm(pred - t[va], axis=1).mean())
        if err < best_err:
            best, best_err = res.x, err
    fit_s = time.time() - t0
    f, _ = forward(best, h, sx.fwd(xt))
    pred = positions_from(args.mode, xt, sy.inv(f))
    return {"test": stats(pred, tt), "hidden": h, "validation_mean_mm": best_err,
            "fit_seconds": fit_s}


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("train")
    p.add_argument("test")
    p.add_argument("--mode", choices=["absolute", "residual"], default="absolute")
    p.add_argument("--hidden", type=int, default=20)
    p.add_argument("--restarts", type=int, default=2)
    p.add_argument("--max-nfev", type=int, default=400)
    p.add_argument("--grid", choices=["paper", "wide", "none"], default="none")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--skip-nn", action="store_true")
    p.add_argument("--skip-svr", action="store_true")
    args = p.parse_args()
    x, t = load(args.train)
    xt, tt = load(args.test)
    out = {"mode": args.mode, "train_points": int(len(x)), "test_points": int(len(xt)),
           "raw": stats(xt, tt)}
    if not args.skip_svr:
        out["svr"] = svr_reference(args, x, t, xt, tt)
    if not args.skip_nn:
        out["nn"] = nn_reference(args, x, t, xt, tt)
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
