"""``station report LOG.mcap [-o DIR]``: the figures of a run, from its log (matplotlib, Agg).

* ``trajectory.png`` (the paper's Fig. 4): robot path, object estimate with 3-sigma ellipses along
  the walk, observation rays (from the camera along psi + phi to the final estimate's range), truth.
* ``cameras.png`` (Fig. 6): keyframe camera poses (optical axes) around the carved model.
* ``errors.png`` (Fig. 7, with simulator truth only): robot localization error, object centre
  error and width error 2 (r - r_true) along the walk.
* ``progress.png``: coverage and the position and radius standard deviations over time.
"""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any, Dict, List, Optional, Union

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from scipy.spatial import ConvexHull  # noqa: E402
from tqdm import tqdm  # noqa: E402

from agent.ekf import position_std  # noqa: E402
from nao_core.protocol import Truth, decode  # noqa: E402
from station.foxglove import ellipse_points  # noqa: E402
from station.mcap_log import LogError, read_log  # noqa: E402
from station.topics import COVERAGE, EKF, KEYFRAME, MEASUREMENT, POSE, TRUTH  # noqa: E402


@dataclass
class RunSeries:
    """The time series a report needs, read once from the log."""

    poses: List[Dict[str, Any]] = field(default_factory=list)
    ekf: List[Dict[str, Any]] = field(default_factory=list)
    measurements: List[Dict[str, Any]] = field(default_factory=list)
    coverage: List[Dict[str, Any]] = field(default_factory=list)
    keyframes: List[Dict[str, Any]] = field(default_factory=list)
    truth: List[Truth] = field(default_factory=list)

    @classmethod
    def read(cls, log_path: Union[str, Path]) -> "RunSeries":
        series = cls()
        lists = {POSE: series.poses, EKF: series.ekf, MEASUREMENT: series.measurements,
                 COVERAGE: series.coverage, KEYFRAME: series.keyframes}
        for message in read_log(log_path, topics={*lists, TRUTH}):
            if message.topic == TRUTH:
                series.truth.append(decode(message.data, Truth))
            else:
                lists[message.topic].append(message.json())
        series.ekf = [e for e in series.ekf if e["x"] is not None]
        return series

    @cached_property
    def _truth_stamps(self) -> List[float]:
        """Stamps of ``truth``, built once (truth_at runs for every pose)."""
        return [tr.stamp for tr in self.truth]

    def truth_at(self, stamp: float) -> Optional[Truth]:
        """The truth message nearest in (bridge) time to ``stamp``."""
        if not self.truth:
            return None
        stamps = self._truth_stamps
        i = bisect.bisect_left(stamps, stamp)
        candidates = [j for j in (i - 1, i) if 0 <= j < len(stamps)]
        return self.truth[min(candidates, key=lambda j: abs(stamps[j] - stamp))]


def write_report(log_path: Union[str, Path], out_dir: Union[str, Path], mesh=None, progress: bool = True) -> List[Path]:
    """Write the figures into ``out_dir``; ``mesh`` (trimesh) is drawn in cameras.png when given."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    series = RunSeries.read(log_path)
    if not (series.poses or series.ekf):
        raise LogError(f"{log_path}: no robot pose and no object estimate in the log: nothing to draw")
    figures = [("trajectory.png", lambda s: _trajectory(s, mesh)), ("cameras.png", lambda s: _cameras(s, mesh)),
               ("progress.png", _progress)]
    if series.truth:
        figures.append(("errors.png", _errors))
    written = []
    for name, draw in tqdm(figures, desc="report", unit="figure", disable=not progress):
        fig = draw(series)
        path = out / name
        fig.savefig(path, dpi=120, bbox_inches="tight")
        plt.close(fig)
        written.append(path)
    return written


def _trajectory(s: RunSeries, mesh=None):
    """The walk, the rays, the filter's estimate and, with ``mesh``, the carved model's footprint and extent."""
    fig, ax = plt.subplots(figsize=(7, 7))
    if s.poses:
        xy = np.array([p["pose"][:2] for p in s.poses])
        ax.plot(xy[:, 0], xy[:, 1], "-", color="tab:blue", lw=1.5, label="robot (localized)")
    if s.truth:
        true_xy = np.array([tr.robot_pose[:2] for tr in s.truth])
        ax.plot(true_xy[:, 0], true_xy[:, 1], ":", color="k", lw=1, label="robot (truth)")
    final = s.ekf[-1]["x"] if s.ekf else None
    for m in s.measurements[:: max(1, len(s.measurements) // 40)]:
        cx, cy, psi = m["cam"]
        heading = psi + m["phi"]
        rng = math.hypot(final[0] - cx, final[1] - cy) if final else 1.0  # rays end at the final estimate's range
        ax.plot([cx, cx + rng * math.cos(heading)], [cy, cy + rng * math.sin(heading)], "-", color="tab:orange", lw=0.4, alpha=0.6)
    for e in s.ekf[:: max(1, len(s.ekf) // 8)] + s.ekf[-1:]:
        ring = ellipse_points(e["x"], np.asarray(e["P"])[:2, :2])
        ax.plot(*np.vstack([ring, ring[:1]]).T, "-", color="tab:red", lw=0.8, alpha=0.7)
    if s.ekf:
        x = s.ekf[-1]["x"]
        ax.add_patch(plt.Circle(x[:2], x[2], fill=False, color="tab:red", lw=2, label="estimate (3-sigma ellipses)"))
    if s.truth:
        obj = s.truth[-1].object
        ax.add_patch(plt.Circle(tuple(obj.centre), obj.radius, fill=False, color="k", ls="--", lw=1.5, label="object (truth)"))
    if mesh is not None and len(mesh.faces):
        xy = mesh.vertices[:, :2]
        outline = xy[ConvexHull(xy).vertices]
        ax.fill(*outline.T, color="tab:green", alpha=0.35, label="carved model (footprint)")
        centre, extent = mesh.vertices.mean(axis=0), np.ptp(mesh.vertices, axis=0)
        text = f"model: centre ({centre[0]:.3f}, {centre[1]:.3f}) m, extent {extent[0]:.3f} x {extent[1]:.3f} x {extent[2]:.3f} m"
        if s.ekf:
            x = s.ekf[-1]["x"]
            text += f"\nfilter: centre ({x[0]:.3f}, {x[1]:.3f}) m, diameter {2 * x[2]:.3f} m"
        ax.text(0.02, 0.98, text, transform=ax.transAxes, fontsize=8, va="top", bbox={"fc": "white", "alpha": 0.8})
    region = [p["pose"][:2] for p in s.poses] + [e["x"][:2] for e in s.ekf[-1:]]
    if region:  # the early ellipses are metres wide: frame the walk and the final estimate
        lo, hi = np.min(region, axis=0) - 0.3, np.max(region, axis=0) + 0.3
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[1], hi[1])
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title("Trajectory, estimate and observation rays")
    ax.legend(loc="lower right", fontsize=8)
    ax.grid(alpha=0.3)
    return fig


def _cameras(s: RunSeries, mesh):
    fig = plt.figure(figsize=(7, 6))
    ax = fig.add_subplot(projection="3d")
    if mesh is not None and len(mesh.faces):
        ax.plot_trisurf(*mesh.vertices.T, triangles=mesh.faces, color="lightgrey", alpha=0.8, linewidth=0)
    for k in s.keyframes:
        T = np.asarray(k["T_WC"]).reshape(4, 4)
        c, z = T[:3, 3], T[:3, 2]
        ax.quiver(*c, *(0.15 * z), color="tab:green", linewidth=0.8)
        ax.scatter(*c, color="tab:green", s=6)
    points = [np.asarray(k["T_WC"]).reshape(4, 4)[:3, 3] for k in s.keyframes]
    if mesh is not None and len(mesh.faces):
        points += list(mesh.vertices)
    if points:  # metric axes: equal scale on x, y, z
        lo, hi = np.min(points, axis=0), np.max(points, axis=0)
        centre, half = 0.5 * (lo + hi), 0.5 * max(float(np.max(hi - lo)), 0.1)
        ax.set_xlim(centre[0] - half, centre[0] + half)
        ax.set_ylim(centre[1] - half, centre[1] + half)
        ax.set_zlim(0.0, half)
        ax.set_box_aspect((1, 1, 0.5))
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_zlabel("z (m)")
    ax.set_title(f"{len(s.keyframes)} keyframe cameras around the model")
    return fig


def _errors(s: RunSeries):
    fig, (a1, a2) = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
    t0 = s.poses[0]["t"] if s.poses else (s.ekf[0]["t"] if s.ekf else 0.0)
    loc = [(p["t"] - t0, p, s.truth_at(p["stamp"])) for p in s.poses]
    if loc:
        a1.plot([t for t, _, _ in loc], [100 * math.hypot(p["pose"][0] - tr.robot_pose[0], p["pose"][1] - tr.robot_pose[1]) for _, p, tr in loc],
                color="tab:blue", label="robot position error")
    obj = s.truth[-1].object
    if s.ekf:
        t = [e["t"] - t0 for e in s.ekf]
        a1.plot(t, [100 * math.hypot(e["x"][0] - obj.centre[0], e["x"][1] - obj.centre[1]) for e in s.ekf], color="tab:red", label="object centre error")
        a2.plot(t, [1000 * 2 * (e["x"][2] - obj.radius) for e in s.ekf], color="tab:purple", label="width error 2(r - r_true)")
    a1.set_ylabel("error (cm)")
    a2.set_ylabel("error (mm)")
    a2.set_xlabel("time (s)")
    for ax in (a1, a2):
        ax.legend(fontsize=8)
        ax.grid(alpha=0.3)
    a1.set_title("Localization and width errors against simulator truth")
    return fig


def _progress(s: RunSeries):
    fig, (a1, a2) = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
    t0 = min([series[0]["t"] for series in (s.coverage, s.ekf) if series], default=0.0)
    if s.coverage:
        a1.plot([c["t"] - t0 for c in s.coverage], [100 * c["fraction"] for c in s.coverage], color="tab:green")
    a1.set_ylabel("coverage (%)")
    if s.ekf:
        t = [e["t"] - t0 for e in s.ekf]
        P = np.array([e["P"] for e in s.ekf])
        a2.semilogy(t, [1000 * position_std(p) for p in P], label="centre std (largest axis)")
        a2.semilogy(t, 1000 * np.sqrt(np.maximum(P[:, 2, 2], 0)), label="radius std")
    a2.set_ylabel("std (mm)")
    a2.set_xlabel("time (s)")
    for ax in (a1, a2):
        ax.grid(alpha=0.3)
    a2.legend(fontsize=8)
    a1.set_title("Coverage and uncertainty")
    return fig
