"""Live space carving in a worker thread, fed with keyframes; never blocks the control loop.

``submit`` only enqueues (mask, T_WC, estimate). The worker creates its carver at the first
keyframe whose estimate is certain enough (largest centre std <= ``max_position_std``), with the
volume around that estimate (:func:`agent.carving.volume_bounds`, which widens it by
``sigma_scale`` standard deviations), carves the keyframes kept so far and then each one as it
comes: the live hull, for progress and the log. ``finish`` drains the queue and carves the final
model in a volume around the *final* estimate from at most ``keyframes`` of them, chosen around that
estimate for azimuth spread and quality (:func:`agent.keyframes.select_keyframes`; the grid does not
depend on the order of views, so this equals ``station carve`` on the log with the same parameters); an estimate
still too uncertain gets no model (a box metres wide would take minutes and carve nothing useful),
and ``error`` says why.
"""

from __future__ import annotations

import queue
import threading
from typing import Callable, Dict, List, Optional, Sequence, Tuple

import numpy as np

from agent.camera import CameraModel
from agent.carving import (
    CarvingParams,
    HullMetrics,
    VoxelCarver,
    carve_consistent,
    estimate_footprint,
    volume_bounds,
)
from agent.ekf import position_std
from agent.keyframes import axis_in_view, select_keyframes, view_azimuth

View = Tuple[np.ndarray, CameraModel, np.ndarray]


def carve_views(views: List[View], x: np.ndarray, P: Optional[np.ndarray], params: CarvingParams,
                pitch: Optional[float] = None, images: Sequence[Optional[np.ndarray]] = (),
                qualities: Sequence[float] = ()) -> VoxelCarver:
    """The final model: the chosen views carved in the volume around the estimate (x, P).

    Views whose pose the estimate contradicts (the axis through x misses their silhouette,
    :func:`agent.keyframes.axis_in_view`) are left out. The others are chosen by
    :func:`agent.keyframes.select_keyframes` from their azimuths around x and their ``qualities``
    (one per view, agent/keyframes.py; all 1 when not given). Raises ValueError when
    the estimate is still too uncertain for the volume to fit ``max_voxels`` (a box metres wide would
    take minutes and carve nothing useful). ``images`` (BGR, one per view or None) colour the model's mesh.
    """
    if qualities and len(qualities) != len(views):
        raise ValueError(f"qualities: {len(qualities)} given for {len(views)} views")
    consistent = [i for i, (mask, camera, T) in enumerate(views) if axis_in_view(mask, camera, T, x[:2], params.max_height)]
    if consistent:  # none: the estimate, not every pose, is off; carve them all
        views = [views[i] for i in consistent]
        images = [images[i] for i in consistent] if images else ()
        qualities = [qualities[i] for i in consistent] if qualities else ()
    chosen = select_keyframes([view_azimuth(T, x[:2]) for _, _, T in views], list(qualities) or [1.0] * len(views),
                              params.keyframes, params.keyframe_gap)
    views = [views[i] for i in chosen]
    images = [images[i] for i in chosen] if images else ()
    lo, hi = volume_bounds(x[:2], float(x[2]), params, P, views)
    return carve_consistent(views, lo, hi, pitch, params, estimate_footprint(lo, hi), images)


class CarvingWorker:
    def __init__(self, params: CarvingParams, camera: CameraModel, max_position_std: float,
                 on_progress: Callable[[HullMetrics, int], None] = lambda metrics, views: None):
        self.params = params
        self.max_position_std = max_position_std
        self.camera = camera
        self.views: List[View] = []
        self.images: List[Optional[np.ndarray]] = []  # the keyframes' BGR images, for the mesh's colours
        self.qualities: List[float] = []  # agent/keyframes.py, for the final choice of views
        self.seqs: List[int] = []  # each view's frame
        self.live: Optional[VoxelCarver] = None
        self.error: Optional[str] = None
        self._on_progress = on_progress
        self._queue: "queue.Queue[Optional[Tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, Optional[np.ndarray], float, CameraModel, int]]]" = queue.Queue()
        self._thread = threading.Thread(target=self._run, name="carving", daemon=True)
        self._thread.start()

    def submit(self, mask: np.ndarray, T_WC: np.ndarray, x: np.ndarray, P: np.ndarray,
               image: Optional[np.ndarray] = None, quality: float = 1.0, camera: Optional[CameraModel] = None,
               seq: int = -1) -> None:
        """Queue a keyframe; ``camera``: the intrinsics it was seen with (default: the worker's), ``seq``
        its frame's (for ``finish``'s poses)."""
        self._queue.put((mask, T_WC, x.copy(), P.copy(), image, quality, camera or self.camera, seq))

    def finish(self, x: Optional[np.ndarray], P: Optional[np.ndarray], poses: Optional[Dict[int, np.ndarray]] = None,
               timeout: float = 60.0) -> Optional[VoxelCarver]:
        """Stop the worker and carve the final model (None without keyframes or an estimate, or when the
        volume is refused: ``error`` says why); ``poses``: T_WC by frame seq, replacing the views' own
        (the smoothed keyframe poses, agent/pose_smoother.py)."""
        self._queue.put(None)
        self._thread.join(timeout)
        if x is None or not self.views:
            return None
        std = position_std(P)
        if std > self.max_position_std:
            self.error = f"no final model: centre std {std:.3f} m > {self.max_position_std:g} m"
            return None
        poses = poses or {}
        views = [(mask, camera, poses.get(seq, T_WC)) for (mask, camera, T_WC), seq in zip(self.views, self.seqs)]
        try:
            return carve_views(views, x, P, self.params, images=self.images if any(i is not None for i in self.images) else (),
                               qualities=self.qualities)
        except ValueError as exc:  # e.g. the estimate is still too uncertain for a bounded volume
            self.error = f"final carving failed: {exc}"
            return None

    def _run(self) -> None:
        while True:
            item = self._queue.get()
            if item is None:
                return
            mask, T_WC, x, P, image, quality, camera, seq = item
            view = (mask, camera, T_WC)
            self.views.append(view)
            self.images.append(image)
            self.qualities.append(quality)
            self.seqs.append(seq)
            if self.error is not None:
                continue
            try:
                if self.live is None:
                    if position_std(P) > self.max_position_std:
                        continue
                    self.live = VoxelCarver.from_estimate(x[:2], float(x[2]), self.params, P, self.views)
                    for kept in self.views[:-1]:
                        self.live.add_view(*kept)
                self.live.add_view(*view)
                self._on_progress(self.live.metrics(), len(self.views))
            except ValueError as exc:  # e.g. a volume too large for max_voxels: keep the views, say why
                self.error = f"live carving stopped: {exc}"
