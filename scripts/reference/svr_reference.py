#!/usr/bin/env python3
"""Write the libsvm reference fixture for the Rust epsilon-SVR solver.

Usage (from the repository root; needs `pip install scikit-learn numpy scipy`):

    python3 scripts/reference/svr_reference.py host/tests/model/fixtures/svr_libsvm.json

It draws a fixed small 3-D regression problem (already standardized, so both
sides see identical numbers), fits scikit-learn's SVR (libsvm: RBF kernel,
WSS2 SMO with shrinking) per output axis for a few (C, epsilon, gamma, tol)
cases, and writes the data, libsvm's dense dual coefficients
(alpha - alpha*), intercepts, dual objective values and predictions on train
and test points to JSON. `host/tests/model/learn.rs` reads the committed fixture, so
CI never needs Python.

The dual objective is libsvm's `obj`:
    0.5 c^T K c - z^T c + epsilon * sum |c|,   c = alpha - alpha*
(at the optimum alpha_i alpha*_i = 0, so sum(alpha + alpha*) = sum |c|).
"""
import json
import sys

import numpy as np
import sklearn
from sklearn.svm import SVR

CASES = [
    # name, C, epsilon, gamma, tol
    ("paper", 100.0, 0.01, 0.5, 1e-3),
    ("bounded", 3.0, 0.05, 2.0, 1e-3),
    ("tight", 10.0, 0.01, 0.5, 1e-6),
]


def field(x):
    """A smooth 3-output function of standardized positions."""
    return np.stack(
        [
            np.sin(1.1 * x[:, 1] + 0.3) * np.cos(0.7 * x[:, 2]) + 0.3 * x[:, 0] ** 2,
            np.cos(0.9 * x[:, 0] - 0.2) * np.sin(0.8 * x[:, 2]) + 0.2 * x[:, 1] * x[:, 2],
            np.sin(1.2 * x[:, 0] + 0.5 * x[:, 1]) + 0.1 * x[:, 2] ** 3,
        ],
        axis=1,
    )


def rbf(a, b, gamma):
    d2 = ((a[:, None, :] - b[None, :, :]) ** 2).sum(axis=2)
    return np.exp(-gamma * d2)


def main():
    out = sys.argv[1] if len(sys.argv) > 1 else "host/tests/model/fixtures/svr_libsvm.json"
    rng = np.random.default_rng(20240611)
    n, m = 300, 100
    x = rng.uniform(-1.7, 1.7, size=(n, 3))
    y = field(x) + 0.02 * rng.standard_normal((n, 3))
    xt = rng.uniform(-1.7, 1.7, size=(m, 3))
    cases = []
    for name, c, eps, gamma, tol in CASES:
        k = rbf(x, x, gamma)
        axes = []
        for a in range(3):
            svr = SVR(kernel="rbf", C=c, epsilon=eps, gamma=gamma, tol=tol,
                      shrinking=True, cache_size=500)
            svr.fit(x, y[:, a])
            coef = np.zeros(n)
            coef[svr.support_] = svr.dual_coef_[0]
            obj = 0.5 * coef @ k @ coef - y[:, a] @ coef + eps * np.abs(coef).sum()
            axes.append(
                {
                    "coef": coef.tolist(),
                    "intercept": float(svr.intercept_[0]),
                    "objective": float(obj),
                    "n_support": int(len(svr.support_)),
                    "n_iter": int(np.asarray(svr.n_iter_).ravel()[0]),
                    "pred_train": svr.predict(x).tolist(),
                    "pred_test": svr.predict(xt).tolist(),
                }
            )
        cases.append({"name": name, "c": c, "epsilon": eps, "gamma": gamma,
                      "tol": tol, "axes": axes})
    doc = {
        "generator": "scripts/reference/svr_reference.py",
        "sklearn_version": sklearn.__version__,
        "x_train": x.tolist(),
        "y_train": y.tolist(),
        "x_test": xt.tolist(),
        "cases": cases,
    }
    with open(out, "w") as f:
        json.dump(doc, f)
    for case in cases:
        print(case["name"], [ax["objective"] for ax in case["axes"]],
              [ax["n_support"] for ax in case["axes"]],
              [ax["n_iter"] for ax in case["axes"]])


if __name__ == "__main__":
    main()
