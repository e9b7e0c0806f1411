"""The small interface every surface-fitting method implements, and what they share.

A *method* (SparseOcc, Neural-Pull, DiGS, ...) turns a point cloud in the unit frame into a
`FittedField`: a torch module plus the rule that turns its output into an "inside score" whose
``level`` iso-surface is the reconstructed surface. Everything downstream (meshing, SDF, query,
weights) talks to `FittedField` only, so methods are interchangeable (nerfstudio-style).
"""

from __future__ import annotations

import math
import time
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import Any, ClassVar

import numpy as np
import torch
from scipy.spatial import cKDTree

from ..errors import JobCanceled


@dataclass
class FitProgress:
    """One progress report from a running fit (unit-free except where named)."""

    iteration: int
    iterations: int
    loss: float
    elapsed_s: float
    message: str = ""


ProgressFn = Callable[[FitProgress], None]
CancelFn = Callable[[], bool]


@dataclass
class FittedField:
    """A trained implicit field in the unit frame ([-1, 1]^3 holds the input).

    module: torch module mapping (B, 3) unit coordinates to raw outputs.
    arch: how to rebuild the module (`ribpull_core.fields.build_module(arch)`), saved with the weights.
    kind: "occupancy" (outputs are 2 logits [out, in]) or "sdf" (output is a signed distance in unit
        frame units, negative inside).
    level: iso-value of `inside_score` that is the surface (SparseOcc: median U at the input points).
    method: name of the method that produced it; config: its config as a plain dict.
    """

    module: torch.nn.Module
    kind: str
    arch: dict[str, Any] = field(default_factory=dict)  # {"name": ..., "kwargs": {...}}: rebuilds `module`
    level: float = 0.0
    method: str = ""
    config: dict[str, Any] = field(default_factory=dict)
    iterations_run: int = 0
    fit_seconds: float = 0.0
    loss_history: list[float] = field(default_factory=list)
    #: name -> final (recent mean) weighted value of each loss term, as summed into the total
    loss_terms: dict[str, float] = field(default_factory=dict)

    @property
    def device(self) -> torch.device:
        return next(self.module.parameters()).device

    def _raw(self, x_unit: torch.Tensor) -> torch.Tensor:
        return self.module(x_unit)

    def inside_score_t(self, x_unit: torch.Tensor) -> torch.Tensor:
        """(B, 3) -> (B,): larger inside; occupancy: U = p_in - p_out in [-1, 1]; sdf: -f."""
        out = self._raw(x_unit)
        if self.kind == "occupancy":
            p = torch.softmax(out, dim=-1)
            return p[..., 1] - p[..., 0]
        return -out.reshape(-1)

    @torch.no_grad()
    def evaluate(self, x_unit: np.ndarray, batch: int = 65536) -> dict[str, np.ndarray]:
        """Evaluate at (N, 3) unit-frame points, in batches, without gradients.

        Returns dict with "inside_score" (N,), "occupancy" (N,) = probability of being inside
        (for sdf methods a logistic of the signed distance, scale 0.01 unit), and "U" (N,) margin
        uncertainty (occupancy methods; for sdf methods 2*occupancy-1).
        """
        x_unit = np.asarray(x_unit, dtype=np.float32).reshape(-1, 3)
        dev = self.device
        self.module.eval()
        scores, occs = [], []
        for i in range(0, len(x_unit), batch):
            xb = torch.from_numpy(x_unit[i : i + batch]).to(dev)
            out = self._raw(xb)
            if self.kind == "occupancy":
                p = torch.softmax(out, dim=-1)
                s = p[..., 1] - p[..., 0]
                o = p[..., 1]
            else:
                s = -out.reshape(-1)
                o = torch.sigmoid(s / 0.01)
            scores.append(s.float().cpu().numpy())
            occs.append(o.float().cpu().numpy())
        score = np.concatenate(scores) if scores else np.zeros(0, np.float32)
        occ = np.concatenate(occs) if occs else np.zeros(0, np.float32)
        return {"inside_score": score, "occupancy": occ, "U": score if self.kind == "occupancy" else 2 * occ - 1}


@dataclass
class KnownOccupancy:
    """Points whose side of the surface the input states (a label map's voxel centres), unit frame.

    points: (M, 3); inside: (M,) bool; distance: (M,) distance to the nearest sample of the other
    class (unit-frame units; the surface lies somewhere in between).

    solid_distance / unit_to_index: the solid the input states as a signed distance volume
    (X, Y, Z) (unit-frame units, negative inside) and the (3, 4) affine from a unit-frame point to
    its fractional node index, or None (a warm start, `GridOccupancyField.set_prior`)."""

    points: np.ndarray
    inside: np.ndarray
    distance: np.ndarray
    solid_distance: np.ndarray | None = None
    unit_to_index: np.ndarray | None = None


class Method(ABC):
    """A surface-fitting method as a *model*: it supplies a network, parameter groups and named loss
    terms; the one training loop (`training.train`) does the rest. Subclasses set `name`, `kind`,
    `config_class` and `presets`; their config has a `schedule` (training.ScheduleConfig) and `seed`.
    """

    name: ClassVar[str]
    #: "occupancy" (2 logits [out, in]) or "sdf" (signed distance, negative inside)
    kind: ClassVar[str]
    config_class: ClassVar[type]
    #: named configs of this method: "paper" (the reference configuration), "default" (what RibPull
    #: runs by default) and "smoke" (seconds, for tests). Each is a zero-argument factory.
    presets: ClassVar[dict[str, Callable[[], Any]]] = {}

    def __init__(self, config: Any = None, unit_mm: float | None = None):
        """unit_mm: millimetres per unit-frame unit of the points the method will be fitted to
        (the pipeline passes its UnitFrame's half_extent_mm); None when unknown, and then config
        lengths stated in mm do not apply."""
        self.config = config if config is not None else self.presets["default"]()
        self.unit_mm = unit_mm

    @abstractmethod
    def arch(self) -> dict:
        """{"name": network, "kwargs": {...}} for `fields.build_module` (saved with the weights)."""

    @abstractmethod
    def setup(self, points_unit: np.ndarray, device: torch.device, known: KnownOccupancy | None = None,
              labels: np.ndarray | None = None) -> None:
        """Prepare everything sampled once (queries, labels, generators) for (N, 3) unit-frame points.
        Runs before `arch`, so the network may depend on the data (e.g. its sampling density).
        `known`: occupancy the input states (label maps); `labels`: (N,) the structure (label value)
        of each point, when the input has them; methods that cannot use either ignore it."""

    def initialize(self, module: torch.nn.Module) -> None:
        """Set the freshly built module's starting state (warm start); default: its own init."""

    def get_param_groups(self, module: torch.nn.Module) -> list[dict]:
        """Optimiser groups [{"params": ..., "base_lr": ...}]; default: one group at schedule.lr."""
        return [{"params": module.parameters(), "base_lr": self.config.schedule.lr}]

    @abstractmethod
    def get_loss_dict(self, module: torch.nn.Module, step: int) -> dict[str, torch.Tensor]:
        """Named, weighted scalar loss terms of one step; the loop minimises their sum."""

    def surface_level(self, fitted: FittedField, points_unit: np.ndarray) -> float:
        """Iso-value of `inside_score` that is the surface (default 0)."""
        return 0.0

    def config_dict(self) -> dict:
        """The config as a plain (nested) dict, saved in model.json."""
        return asdict(self.config)

    def fit(
        self,
        points_unit: np.ndarray,
        device: torch.device,
        progress: ProgressFn | None = None,
        should_cancel: CancelFn | None = None,
        known: KnownOccupancy | None = None,
        labels: np.ndarray | None = None,
    ) -> FittedField:
        """Fit to (N, 3) float unit-frame points (labels: (N,) their structures, optional) with the
        shared training loop; return the field."""
        from .training import train

        return train(self, points_unit, device, progress, should_cancel, known, labels)


# --- shared training helpers -------------------------------------------------------------------

def check_cancel(should_cancel: CancelFn | None) -> None:
    """Raise JobCanceled when the caller asked to stop (checked inside training loops)."""
    if should_cancel is not None and should_cancel():
        raise JobCanceled("canceled")


def warmup_cosine_lr(iteration: int, total: int, base_lr: float, warmup: int, final_ratio: float = 0.0) -> float:
    """Linear warm-up over `warmup` iterations, then cosine decay to final_ratio*base_lr (Neural-Pull/SparseOcc)."""
    if warmup > 0 and iteration < warmup:
        return base_lr * (iteration + 1) / warmup
    t = (iteration - warmup) / max(1, total - warmup)
    t = min(max(t, 0.0), 1.0)
    return base_lr * (final_ratio + (1 - final_ratio) * 0.5 * (1 + math.cos(math.pi * t)))


def knn_sigma(points: np.ndarray, k: int = 50, tree: cKDTree | None = None) -> np.ndarray:
    """(N,) distance from each point to its k-th nearest neighbour (Neural-Pull's local scale);
    tree: a kd-tree of `points` to reuse."""
    from ..neighbours import kth_neighbour_distance

    # the (k+1)-th point (the point itself is the first), on a cell grid: the kd-tree's values
    return kth_neighbour_distance(points, int(min(k, len(points) - 1)) + 1, tree)


def sample_pull_queries(
    points: np.ndarray,
    total_queries: int,
    rng: np.random.Generator,
    k: int = 50,
    scale: float | None = None,
    sigma: np.ndarray | None = None,
    tree: cKDTree | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Neural-Pull query sampling around the input points.

    points: (N, 3) unit frame. Each point spawns ~total_queries/N queries q = p + s*sigma_p*N(0, I),
    sigma_p = distance to the k-th neighbour (pass `sigma`/`tree` to reuse them across calls),
    s = 0.25*sqrt(N/20000) unless given.
    Returns (queries (Q, 3) float32, index (Q,) of the nearest input point of each query).
    """
    n = len(points)
    tree = tree if tree is not None else cKDTree(points)
    if sigma is None:
        sigma = knn_sigma(points, k)
    if scale is None:
        scale = 0.25 * math.sqrt(n / 20000.0)
    per = max(1, round(total_queries / n))
    src = np.repeat(np.arange(n), per)
    q = points[src] + (scale * sigma[src])[:, None] * rng.standard_normal((len(src), 3))
    _, nn = tree.query(q, k=1, workers=-1)
    return q.astype(np.float32), nn.astype(np.int64)


def seed_everything(seed: int) -> None:
    """Make numpy/torch deterministic for a given seed (CPU; CUDA kernels may still vary)."""
    np.random.seed(seed % (2**32))
    torch.manual_seed(seed)


class ProgressThrottle:
    """Call `progress` at most every `interval_s` seconds (and always on the last iteration)."""

    def __init__(self, progress: ProgressFn | None, total: int, interval_s: float = 0.5):
        self.progress, self.total, self.interval = progress, total, interval_s
        self.t0 = time.perf_counter()
        self._last = -1e9

    def __call__(self, iteration: int, loss: float, message: str = "") -> None:
        now = time.perf_counter()
        if self.progress is None:
            return
        if now - self._last >= self.interval or iteration + 1 >= self.total:
            self._last = now
            self.progress(FitProgress(iteration + 1, self.total, float(loss), now - self.t0, message))
