"""Proof check: the polynomial solvers find the global minimum of their algebraic cost.

ASPnP and OPnP claim to return *all* real stationary points of their cost (Macaulay null-space
solver, :mod:`cutterpose.solvers.pnp.polysolve`). This script checks it against an independent
method:
a dense multi-start local minimisation of the same cost from many random starts (damped Newton
descent from every start, vectorised; the distinct end points finished by
``scipy.optimize.minimize``, trust-region Newton with the exact gradient and Hessian).

For every instance (random protocol pose, planar holder or non-planar points, Gaussian noise
sigma uniform in [0, sigma_max] px) and every cost

* OPnP: ``f(q) = w(q)^T G w(q)`` over ``q in R^4``;
* ASPnP case 1: ``F(1, b, c, d)`` over ``(b, c, d) in R^3``;
* ASPnP case 2: ``F(0, 1, c, d)`` over ``(c, d) in R^2``,

it compares the least cost over our stationary points with the best multi-start minimum and
counts an instance as *worse* when ``ours > best + 1e-9 |best| + 1e-13 s``, where
``s = |w|^T |G| |w|`` (``|mu|^T |M| |mu|`` for ASPnP) at the two points bounds the rounding error
of evaluating the cost (noise-free instances have both costs ~0, up to that rounding). It
also counts multi-start local minima that are not among our stationary points (``missed``).

Usage::

    python benchmarks/check_stationary.py --instances 1000 --starts 200
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402
from scipy.optimize import minimize  # noqa: E402

from cutterpose.geometry.camera import default_camera  # noqa: E402
from cutterpose.geometry.holder import default_holder  # noqa: E402
from cutterpose.geometry.pose import rotation_from_euler_deg  # noqa: E402
from cutterpose.solvers.pnp import aspnp, opnp  # noqa: E402

REL_TOL = 1e-9
ROUND_TOL = 1e-13  # times |w|^T |G| |w|: bound on the rounding error of a cost evaluation


def make_instance(rng: np.random.Generator, planar: bool, sigma_px: float, camera=None,
                  holder=None) -> tuple[np.ndarray, np.ndarray]:
    """Object points (mm) and normalised noisy image points of one random protocol pose.

    Poses: alpha, beta, gamma uniform in [-60, 60] deg, X, Y in [-90, 90] mm, Z in 600 +- 90 mm;
    redrawn until every point is in the image. Non-planar: holder corners with Z uniform in
    [-50, 50] mm.
    """
    camera = camera or default_camera("synthetic")
    holder = holder or default_holder()
    P = holder.points_holder_mm.copy()
    if not planar:
        P[:, 2] = rng.uniform(-50.0, 50.0, len(P))
    while True:
        R = rotation_from_euler_deg(*rng.uniform(-60.0, 60.0, 3))
        t = np.array([*rng.uniform(-90.0, 90.0, 2), 600.0 + rng.uniform(-90.0, 90.0)])
        px = camera.project(P @ R.T + t)
        if np.all(np.isfinite(px)) and np.all(camera.in_image(px)):
            break
    px = px + sigma_px * rng.standard_normal(px.shape)
    return P, camera.normalize_px(px)


def _multistart(fun, grad, hess, starts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Local minimisation from every start.

    All starts descend together by Levenberg-Marquardt-damped Newton steps (vectorised over
    the starts; a step is taken only if it lowers the cost, so each run is a monotone descent
    to a local minimum). The distinct end points are then finished by
    ``scipy.optimize.minimize`` (trust-region Newton, exact gradient and Hessian).
    ``fun``, ``grad``, ``hess`` take a batch ``(p, k)``.
    """
    x = np.array(starts, float)
    f = fun(x)
    lam = np.full(len(x), 1e-3)
    eye = np.eye(x.shape[1])
    for _ in range(150):
        g, H = grad(x), hess(x)
        scale = np.abs(np.diagonal(H, axis1=1, axis2=2)).max(axis=1) + 1e-300
        A = H + (lam * scale)[:, None, None] * eye
        try:
            step = np.linalg.solve(A, g[..., None])[..., 0]
        except np.linalg.LinAlgError:
            step = g / scale[:, None]
        x_new = x - step
        f_new = fun(x_new)
        better = np.isfinite(f_new) & (f_new < f)
        x[better], f[better] = x_new[better], f_new[better]
        lam = np.where(better, np.maximum(lam / 3, 1e-12), np.minimum(lam * 4, 1e12))
        small = np.linalg.norm(step, axis=1) <= 1e-13 * (1 + np.linalg.norm(x, axis=1))
        if np.all(small | (lam >= 1e12)):
            break  # every run has converged (or can no longer descend)
    xs, fs = [], []
    for x0 in _distinct(x, f):
        r = minimize(lambda z: float(fun(z[None])[0]), x0, jac=lambda z: grad(z[None])[0],
                     hess=lambda z: hess(z[None])[0], method="trust-exact",
                     options={"gtol": 1e-13, "maxiter": 200})
        xs.append(r.x)
        fs.append(r.fun)
    return np.array(xs), np.array(fs)


def _distinct(x: np.ndarray, f: np.ndarray) -> list[np.ndarray]:
    out: list[np.ndarray] = []
    for xi in x[np.argsort(f)]:
        if all(np.linalg.norm(xi - y) > 1e-6 * (1 + np.linalg.norm(xi)) for y in out):
            out.append(xi)
    return out


def _missed(x_ms, f_ms, ours, sym: bool) -> int:
    """Multi-start minima (distinct, cost within the local-minimum set) absent from ours."""
    missed = 0
    seen: list[np.ndarray] = []
    for x in x_ms[np.argsort(f_ms)]:
        if any(np.linalg.norm(x - y) < 1e-6 * (1 + np.linalg.norm(x)) for y in seen):
            continue
        seen.append(x)
        d = np.linalg.norm(ours - x, axis=1) if len(ours) else np.array([np.inf])
        if sym and len(ours):
            d = np.minimum(d, np.linalg.norm(ours + x, axis=1))
        if d.min() > 1e-5 * (1 + np.linalg.norm(x)):
            missed += 1
    return missed


def check_instance(P: np.ndarray, m: np.ndarray, n_starts: int, rng: np.random.Generator):
    """Rows ``(cost name, ours, best multistart, rounding scale, missed)`` per instance."""
    Pn, _, _ = aspnp.normalise_object(P)
    rows = []
    # --- OPnP: f over R^4; starts: random rotations, |q|^2 = 1/zbar with zbar over a wide range
    sp = opnp.stationary_points(Pn, m)
    G = sp["G"] / np.trace(sp["G"])
    coef = opnp.gradient_coefficients(G)
    sysm = opnp.SYSTEM

    def f(q):
        return opnp.cost(G, q)

    def g(q):
        return sysm.evaluate(coef, q)

    def h(q):
        return sysm.jacobian(coef, q)

    u = rng.standard_normal((n_starts, 4))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    zbar = np.exp(rng.uniform(np.log(0.5), np.log(50.0), n_starts))  # normalised mean depth
    x_ms, f_ms = _multistart(f, g, h, u / np.sqrt(zbar)[:, None])
    # q = 0 (infinite depth) is the trivial stationary point the solver knows and discards as no
    # pose (notes 5.2); the multi-start can descend to it, so it counts as found.
    ours = np.vstack([sp["q"], np.zeros((1, 4))])
    f_all = opnp.cost(G, ours)
    i_o, i_b = int(np.argmin(f_all)), int(np.argmin(f_ms))
    scale = opnp.cost(np.abs(G), np.abs(np.array([ours[i_o], x_ms[i_b]]))).max()
    rows.append(("opnp", f_all[i_o], f_ms[i_b], scale, _missed(x_ms, f_ms, ours, sym=True)))
    # --- ASPnP cases 1 and 2
    sa = aspnp.stationary_points(Pn, m)
    M = sa["M"]
    for case, mp, system, nfree in ((1, aspnp.MAP1, aspnp.SYS1, 3),
                                    (2, aspnp.MAP2, aspnp.SYS2, 2)):
        c = mp @ M.ravel()
        fixed = (aspnp.CASE1_FIXED, aspnp.CASE2_FIXED)[case - 1]
        free = np.isnan(fixed)

        def F(x, fixed=fixed, free=free, M=M):
            q = np.tile(fixed, (len(x), 1))
            q[:, free] = x
            mu = aspnp.mu_of(q)
            return np.einsum("pi,ij,pj->p", mu, M, mu)

        def gF(x, c=c, system=system):
            return system.evaluate(c, x)

        def hF(x, c=c, system=system):
            return system.jacobian(c, x)

        # starts: random rotations written in this case's chart (tan of half-angle scale)
        q0 = rng.standard_normal((n_starts, nfree))
        q0 *= np.tan(rng.uniform(0.0, 0.49 * np.pi, n_starts))[:, None] / \
            np.linalg.norm(q0, axis=1, keepdims=True)
        if case == 2:
            q0 = q0 * 3.0
        x_ms, f_ms = _multistart(F, gF, hF, q0)
        sel = sa["case"] == case
        ours_x = sa["q"][sel][:, free]
        f_all = sa["cost"][sel]
        i_o, i_b = int(np.argmin(f_all)), int(np.argmin(f_ms))
        scale = F(np.abs(np.array([ours_x[i_o], x_ms[i_b]])), M=np.abs(M)).max()
        rows.append((f"aspnp-case{case}", f_all[i_o], f_ms[i_b], scale,
                     _missed(x_ms, f_ms, ours_x, sym=False)))
    return rows


def run_check(n_instances: int, n_starts: int, seed: int = 0, sigma_max: float = 5.0,
              progress: bool = False) -> dict:
    """Run the check; per cost name: worst relative excess, count worse, count with misses."""
    rng = np.random.default_rng(seed)
    cam, holder = default_camera("synthetic"), default_holder()
    out: dict[str, dict] = {}
    t0 = time.perf_counter()
    for i in range(n_instances):
        planar = i % 2 == 0
        sigma = rng.uniform(0.0, sigma_max) if i % 10 else 0.0
        P, m = make_instance(rng, planar, sigma, cam, holder)
        for name, ours, best, scale, missed in check_instance(P, m, n_starts, rng):
            o = out.setdefault(name, {"n": 0, "worse": 0, "worst_excess_rel": -np.inf,
                                      "missed_instances": 0, "missed_minima": 0})
            o["n"] += 1
            excess = ours - best
            rel = excess / max(abs(best), ROUND_TOL * scale)
            o["worst_excess_rel"] = max(o["worst_excess_rel"], rel)
            if excess > REL_TOL * abs(best) + ROUND_TOL * scale:
                o["worse"] += 1
            o["missed_instances"] += missed > 0
            o["missed_minima"] += missed
        if progress and (i + 1) % 50 == 0:
            summary = ", ".join(f"{k}: {o['worse']} worse, {o['missed_instances']} missed"
                                for k, o in out.items())
            print(f"  {i + 1}/{n_instances} instances, {time.perf_counter() - t0:.0f} s; "
                  f"{summary}", flush=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--instances", type=int, default=1000)
    ap.add_argument("--starts", type=int, default=200)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--sigma-max", type=float, default=5.0)
    a = ap.parse_args()
    t0 = time.perf_counter()
    out = run_check(a.instances, a.starts, a.seed, a.sigma_max, progress=True)
    print(f"\n{a.instances} instances (half planar holder, half non-planar), sigma uniform in "
          f"[0, {a.sigma_max}] px (every 10th noise-free), {a.starts} starts per cost, "
          f"seed {a.seed}, {time.perf_counter() - t0:.0f} s")
    print(f"{'cost':14s} {'n':>5s} {'ours worse':>11s} {'worst rel. excess':>18s} "
          f"{'inst. w/ missed min':>20s} {'missed minima':>14s}")
    for name, o in out.items():
        print(f"{name:14s} {o['n']:5d} {o['worse']:11d} {o['worst_excess_rel']:18.2e} "
              f"{o['missed_instances']:20d} {o['missed_minima']:14d}")


if __name__ == "__main__":
    main()
