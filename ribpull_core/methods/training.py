"""THE training loop: one loop for every method (nerfstudio's trainer / model split).

A method is a model, not a loop: it builds its network (`arch`), prepares its data once (`setup`),
names its parameter groups (`get_param_groups`) and returns a dictionary of named, already weighted
loss terms for one step (`get_loss_dict`). Everything else lives here, once: seeding, the Adam
optimiser, the warm-up + cosine schedule, gradient clipping, cancellation, throttled progress,
early stopping, the loss history and the final value of every loss term.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch

from ..fields import build_module
from .base import (
    CancelFn,
    FittedField,
    KnownOccupancy,
    ProgressFn,
    ProgressThrottle,
    check_cancel,
    seed_everything,
    warmup_cosine_lr,
)
from .optimizer import make_optimizer

if TYPE_CHECKING:  # pragma: no cover
    from .base import Method


@dataclass
class ScheduleConfig:
    """The optimiser schedule every method shares (unit-free).

    iterations: optimiser steps at most. lr: base Adam rate (a parameter group may set its own
    "base_lr"). warmup: linear warm-up steps, then cosine decay to final_lr_ratio x lr
    (decay "cosine"), or a constant rate (decay "constant"). grad_clip: max total gradient norm
    (None: no clipping). early_stop_window: steps per window of the convergence test (0: off);
    training stops once the mean loss of the last window improved by less than early_stop_rel_tol
    (relative) on the window before, after at least early_stop_min_fraction of the schedule.
    history_points: about how many window-averaged losses `FittedField.loss_history` keeps.
    """

    iterations: int = 1000
    lr: float = 1e-3
    warmup: int = 0
    final_lr_ratio: float = 0.0
    decay: str = "cosine"
    grad_clip: float | None = None
    early_stop_window: int = 0
    early_stop_rel_tol: float = 0.01
    early_stop_min_fraction: float = 0.3
    history_points: int = 500


def learning_rate(schedule: ScheduleConfig, step: int, base_lr: float) -> float:
    """The rate of a group with base rate `base_lr` at `step` under `schedule`."""
    if schedule.decay == "constant":
        return base_lr
    return warmup_cosine_lr(step, schedule.iterations, base_lr, schedule.warmup, schedule.final_lr_ratio)


class EarlyStop:
    """Window-mean convergence test on the total loss (see ScheduleConfig.early_stop_*)."""

    def __init__(self, schedule: ScheduleConfig):
        self.s = schedule
        self.window_means: list[float] = []
        self._acc: list[float] = []

    def __call__(self, step: int, loss: float) -> bool:
        w = self.s.early_stop_window
        if w <= 0:
            return False
        self._acc.append(loss)
        if len(self._acc) < w:
            return False
        self.window_means.append(float(np.mean(self._acc)))
        self._acc = []
        if step + 1 < self.s.early_stop_min_fraction * self.s.iterations or len(self.window_means) < 2:
            return False
        prev, last = self.window_means[-2], self.window_means[-1]
        return (prev - last) < self.s.early_stop_rel_tol * abs(prev)


class LossLog:
    """Window-averaged total loss (the history) and the recent mean of every named term."""

    def __init__(self, iterations: int, history_points: int, recent: int = 50):
        self.window = max(1, iterations // max(1, history_points))
        self.recent = recent
        self.history: list[float] = []
        self._acc: list[float] = []
        self._terms: dict[str, list[float]] = {}

    def add(self, total: float, terms: dict[str, float]) -> None:
        self._acc.append(total)
        if len(self._acc) == self.window:
            self.history.append(float(np.mean(self._acc)))
            self._acc = []
        for k, v in terms.items():
            vals = self._terms.setdefault(k, [])
            vals.append(v)
            if len(vals) > self.recent:
                del vals[0]

    def close(self) -> None:
        if self._acc:
            self.history.append(float(np.mean(self._acc)))
            self._acc = []

    def final_terms(self) -> dict[str, float]:
        """name -> mean of its last `recent` values (weighted, as added to the total)."""
        return {k: float(np.mean(v)) for k, v in self._terms.items()}


def train(method: Method, points_unit: np.ndarray, device: torch.device, progress: ProgressFn | None = None,
          should_cancel: CancelFn | None = None, known: KnownOccupancy | None = None,
          labels: np.ndarray | None = None) -> FittedField:
    """Fit `method` to (N, 3) unit-frame points on `device`; returns the trained FittedField.

    Calls method.setup once (data sampled once; a method that starts warm may shorten its schedule
    there), builds method.arch(), lets method.initialize the module (warm starts), then each step
    sums the terms of method.get_loss_dict(module, step). Checks `should_cancel` every 10 steps
    (raises JobCanceled) and reports progress about twice a second.
    """
    t0 = time.perf_counter()
    device = torch.device(device)
    seed_everything(method.config.seed)
    points = np.asarray(points_unit, dtype=np.float64).reshape(-1, 3)
    check_cancel(should_cancel)
    method.setup(points, device, known, labels)
    schedule: ScheduleConfig = method.config.schedule  # after setup: a warm start may shorten it
    arch = method.arch()
    module = build_module(arch).to(device).train()
    method.initialize(module)
    groups = [dict(g) for g in method.get_param_groups(module)]
    for g in groups:
        g.setdefault("base_lr", schedule.lr)
        g["params"] = list(g["params"])
        g["lr"] = g["base_lr"]
    opt = make_optimizer(groups, device)
    params = [p for g in groups for p in g["params"]]
    report = ProgressThrottle(progress, schedule.iterations)
    log = LossLog(schedule.iterations, schedule.history_points)
    stop = EarlyStop(schedule)
    step = 0
    for step in range(schedule.iterations):
        if step % 10 == 0:
            check_cancel(should_cancel)
        for g in groups:
            g["lr"] = learning_rate(schedule, step, g["base_lr"])
        terms = method.get_loss_dict(module, step)
        loss = sum(terms.values())
        opt.zero_grad()
        loss.backward()
        if schedule.grad_clip:
            torch.nn.utils.clip_grad_norm_(params, schedule.grad_clip)
        opt.step()
        total = float(loss.detach())
        log.add(total, {k: float(v.detach()) for k, v in terms.items()})
        report(step, total, method.name)
        if stop(step, total):
            break
    log.close()
    module.eval()
    fitted = FittedField(module=module, kind=method.kind, arch=arch, method=method.name,
                         config=method.config_dict(), iterations_run=step + 1,
                         fit_seconds=0.0, loss_history=log.history, loss_terms=log.final_terms())
    fitted.level = method.surface_level(fitted, points)
    fitted.fit_seconds = time.perf_counter() - t0
    return fitted


def with_schedule(config, **changes):
    """A copy of a method config whose schedule has `changes` (e.g. iterations=100)."""
    return dataclasses.replace(config, schedule=dataclasses.replace(config.schedule, **changes))
