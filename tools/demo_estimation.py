"""Demo of the object EKF: a camera circles a cylinder and the estimate converges (cf. the paper's Fig. 4).

Usage: ``python -m tools.demo_estimation --out DIR [--seed N]``. Writes ``estimation_topview.png``
(true object, camera path, estimate with its 3-sigma ellipse at several times) and
``estimation_errors.png`` (centre and radius errors with their 3-sigma bounds over time).

The simulation helpers (:func:`circling_cameras`, :func:`simulate`, :func:`circling_runs`,
:func:`first_views`) are reused by the tests and the benchmark so that all three exercise the filter
on the same synthetic ground truth.
"""

from __future__ import annotations

import argparse
import math
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from agent.ekf import EKFParams, FloorContact, ObjectEKF, floor_depression, load_ekf_params, measure


def circling_cameras(
    centre: Sequence[float], radius: float, n: int, start: float = 0.0, aim_offset: float = 0.0
) -> np.ndarray:
    """``n`` planar camera poses (cx, cy, psi) evenly on one circle around ``centre``, aimed at it + offset."""
    angles = start + 2.0 * math.pi * np.arange(n) / n
    cams = np.empty((n, 3))
    cams[:, 0] = centre[0] + radius * np.cos(angles)
    cams[:, 1] = centre[1] + radius * np.sin(angles)
    cams[:, 2] = angles + math.pi + aim_offset
    return cams


@dataclass(frozen=True)
class Trace:
    """One simulated run: per view the camera, estimate, covariance, NIS (nan at init) and flags."""

    truth: np.ndarray  # (3,)
    cams: np.ndarray  # (N, 3)
    x: np.ndarray  # (N, 3)
    P: np.ndarray  # (N, 3, 3)
    nis: np.ndarray  # (N,)
    accepted: np.ndarray  # (N,) bool
    outlier: np.ndarray  # (N,) bool
    restarts: int = 0  # the filter's re-initializations

    @property
    def nees(self) -> np.ndarray:
        err = self.x - self.truth
        return np.einsum("ni,ni->n", err, np.linalg.solve(self.P, err[..., None])[..., 0])


@dataclass(frozen=True)
class PoseDrift:
    """Errors of the camera poses the filter is told, as a localizer between landmark fixes makes
    them: a random walk of ``step`` (m, per position axis) and ``heading_step`` (rad) std per view,
    reset every ``fix_every`` views to a fix's error of std ``fix`` (m) and ``heading_fix`` (rad)."""

    step: float
    heading_step: float
    fix: float
    heading_fix: float
    fix_every: int

    def draw(self, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """(errors (n, 3), their covariances (n, 3, 3)): what the poses are off by and what a localizer says."""
        fix_var = np.array([self.fix, self.fix, self.heading_fix]) ** 2
        step_var = np.array([self.step, self.step, self.heading_step]) ** 2
        errors, covs = np.empty((n, 3)), np.empty((n, 3, 3))
        for k in range(n):
            since = k % self.fix_every
            errors[k] = rng.normal(0.0, np.sqrt(fix_var)) if since == 0 else errors[k - 1] + rng.normal(0.0, np.sqrt(step_var))
            covs[k] = np.diag(fix_var + since * step_var)
        return errors, covs


def simulate(
    ekf: ObjectEKF,
    truth: np.ndarray,
    cams: np.ndarray,
    rng: np.random.Generator,
    dt: float = 0.1,
    outlier_fraction: float = 0.0,
    drift: Optional[PoseDrift] = None,
    weigh_pose: bool = False,
) -> Trace:
    """Initialize ``ekf`` from the first view, then predict(dt) + update per view; noisy (phi, delta).

    Gross outliers (after the first view): bearing off by 3 to 20 deg and width scaled by 0.5 to 0.75
    or 1.3 to 2, with probability ``outlier_fraction``. With ``drift`` the filter is told camera poses
    off by its errors (the views are of the true ones), and their covariances when ``weigh_pose``.
    """
    p = ekf.params
    errors, covs = drift.draw(len(cams), rng) if drift else (np.zeros((len(cams), 3)), np.zeros((len(cams), 3, 3)))
    z = measure(truth, cams, p.width_model) + rng.normal(0.0, [p.sigma_phi, p.sigma_delta], size=(len(cams), 2))
    outlier = rng.random(len(cams)) < outlier_fraction
    outlier[0] = False
    n_out = int(outlier.sum())
    z[outlier, 0] += rng.choice([-1.0, 1.0], n_out) * np.radians(rng.uniform(3.0, 20.0, n_out))
    z[outlier, 1] *= np.where(rng.random(n_out) < 0.5, rng.uniform(0.5, 0.75, n_out), rng.uniform(1.3, 2.0, n_out))
    xs, Ps, nis, accepted = [], [], [], []
    for k, (cam, (phi, delta)) in enumerate(zip(cams + errors, z)):
        if k == 0:
            result = ekf.initialize(cam, phi, delta)
        else:
            ekf.predict(dt)
            result = ekf.update(cam, phi, delta, covs[k] if weigh_pose else None)
        xs.append(ekf.x.copy())
        Ps.append(ekf.P.copy())
        nis.append(np.nan if result.nis is None else result.nis)
        accepted.append(result.accepted)
    return Trace(np.asarray(truth, float), cams, np.array(xs), np.array(Ps), np.array(nis), np.array(accepted), outlier,
                 ekf.stats.reinitialized)


def circling_runs(
    params: EKFParams, n_runs: int, n_views: int, seed: int, radius_std: float = 0.0, outliers: float = 0.0,
    drift: Optional[PoseDrift] = None, weigh_pose: bool = False,
) -> list[Trace]:
    """Monte-Carlo runs of one circle at 0.5 m around a random object (centre in [-1, 1]^2 m).

    The true radius is 0.07 m, or, when ``radius_std`` > 0, drawn from the prior as the filter models
    it (a truth that matches the model, for consistency checks): the radius prior propagated to first
    order to the inverse radius, 1 / r ~ N(1 / radius_prior, (radius_std / radius_prior^2)^2).
    Random start angle and aim offset; ``drift`` and ``weigh_pose`` as for :func:`simulate`.
    """
    rng = np.random.default_rng(seed)
    traces = []
    r0 = params.radius_prior
    for _ in range(n_runs):
        r = 1.0 / (1.0 / r0 + radius_std / r0**2 * rng.standard_normal()) if radius_std else 0.07
        truth = np.array([*rng.uniform(-1.0, 1.0, 2), r])
        start, aim = rng.uniform(-math.pi, math.pi), rng.uniform(-0.2, 0.2)
        cams = circling_cameras(truth[:2], 0.5, n_views, start=start, aim_offset=aim)
        traces.append(simulate(ObjectEKF(params), truth, cams, rng, outlier_fraction=outliers, drift=drift, weigh_pose=weigh_pose))
    return traces


@dataclass(frozen=True)
class FirstView:
    """One first view of a cylinder ``truth`` (xo, yo, r) from ``cam``: its noisy bearing, width and floor contact."""

    truth: np.ndarray
    cam: np.ndarray
    phi: float
    delta: float
    floor: FloorContact


def first_views(params: EKFParams, n_views: int, seed: int, radii: Optional[tuple[float, float]] = None,
                ranges: tuple[float, float] = (0.6, 2.0), height: float = 0.5) -> list[FirstView]:
    """First views of a cylinder ``ranges`` m ahead (within 0.3 rad of the optical axis), from a camera
    ``height`` m above the floor, with the noise the filter models on (phi, delta) and on the floor
    contact's depression (``floor_angle_std``). The radius is uniform in ``radii``, or drawn from the
    prior N(radius_prior, radius_prior_std^2)."""
    rng = np.random.default_rng(seed)
    views = []
    for _ in range(n_views):
        if radii is None:
            r = params.radius_prior + params.radius_prior_std * rng.standard_normal()
        else:
            r = rng.uniform(*radii)
        truth = np.array([rng.uniform(*ranges), rng.uniform(-0.5, 0.5), r])
        cam = np.array([0.0, 0.0, math.atan2(truth[1], truth[0]) + rng.uniform(-0.3, 0.3)])
        phi, delta = measure(truth, cam) + np.array([params.sigma_phi, params.sigma_delta]) * rng.standard_normal(2)
        depression = floor_depression(truth, cam, height)[0] + params.floor_angle_std * rng.standard_normal()
        views.append(FirstView(truth, cam, float(phi), float(delta), FloorContact(depression, height)))
    return views


def sigma_ellipse(ax, centre: np.ndarray, cov: np.ndarray, sigmas: float = 3.0, **style) -> None:
    """Draw the ``sigmas``-sigma ellipse of the 2x2 covariance ``cov`` around ``centre`` on ``ax``."""
    from matplotlib.patches import Ellipse

    values, vectors = np.linalg.eigh(cov)
    angle = math.degrees(math.atan2(vectors[1, 1], vectors[0, 1]))
    width, height = 2.0 * sigmas * np.sqrt(np.maximum(values[::-1], 0.0))
    ax.add_patch(Ellipse(centre, width, height, angle=angle, fill=False, **style))


def plot(trace: Trace, out: Path) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    truth, x, P = trace.truth, trace.x, trace.P
    n = len(x)

    fig, axes = plt.subplots(1, 3, figsize=(18, 6.2))
    shown = [0, 1, 2, 4, 8, n // 4, n // 2, n - 1]
    colors = plt.cm.viridis(np.linspace(0.0, 1.0, len(shown)))
    for ax, half_width in zip(axes, (1.0, 0.15, 0.01)):
        ax.add_patch(plt.Circle(truth[:2], truth[2], color="0.85", label="true object"))
        ax.plot(*truth[:2], "kx", label="true centre")
        ax.plot(trace.cams[:, 0], trace.cams[:, 1], "k.-", ms=3, lw=0.5, label="camera path")
        for k, color in zip(shown, colors):
            ax.plot(*x[k, :2], "+", color=color)
            sigma_ellipse(ax, x[k, :2], P[k, :2, :2], color=color, lw=1.2, label=f"view {k}: 3-sigma")
            ax.add_patch(plt.Circle(x[k, :2], x[k, 2], fill=False, ls=":", color=color, lw=0.8))
        ax.set_aspect("equal")
        ax.set_xlim(truth[0] - half_width, truth[0] + half_width)
        ax.set_ylim(truth[1] - half_width, truth[1] + half_width)
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
    axes[0].set_title("Estimate and 3-sigma ellipse while circling")
    axes[1].set_title("Zoom +-15 cm (dotted circles: estimated radius)")
    axes[2].set_title("Zoom +-1 cm: the later estimates")
    axes[0].legend(fontsize=7, loc="upper right")
    top = out / "estimation_topview.png"
    fig.savefig(top, dpi=110, bbox_inches="tight")
    plt.close(fig)

    views = np.arange(n)
    err = x - truth
    fig, axes = plt.subplots(3, 1, figsize=(7, 7.5), sharex=True)
    for ax, i, name in zip(axes, range(3), ("x_o", "y_o", "r")):
        sigma = np.sqrt(P[:, i, i])
        ax.fill_between(views, -3e3 * sigma, 3e3 * sigma, color="C0", alpha=0.2, label="3-sigma")
        ax.plot(views, 1e3 * err[:, i], "C3", label="error")
        ax.axhline(0.0, color="k", lw=0.5)
        ax.set_ylabel(f"{name} error (mm)")
        ax.set_ylim(-3e3 * sigma[min(2, n - 1)], 3e3 * sigma[min(2, n - 1)])
        ax.legend(fontsize=7, loc="upper right")
    axes[-1].set_xlabel("view (one circle)")
    axes[0].set_title("Estimation error and 3-sigma bound")
    errors = out / "estimation_errors.png"
    fig.savefig(errors, dpi=120, bbox_inches="tight")
    plt.close(fig)
    return [top, errors]


def main(argv: Optional[list[str]] = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", required=True, type=Path, help="directory for the PNG figures")
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args(argv)
    params = load_ekf_params()
    truth = np.array([1.2, 0.4, 0.08])
    cams = circling_cameras(truth[:2], 0.5, 72, start=0.3, aim_offset=0.15)
    trace = simulate(ObjectEKF(params), truth, cams, np.random.default_rng(args.seed))
    paths = plot(trace, args.out)
    err = trace.x[-1] - truth
    print(
        f"after one circle: centre error {1e3 * math.hypot(err[0], err[1]):.2f} mm, "
        f"radius error {1e3 * err[2]:+.2f} mm, 3-sigma radius {3e3 * math.sqrt(trace.P[-1, 2, 2]):.2f} mm"
    )
    for path in paths:
        print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
