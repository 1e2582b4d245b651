"""Levenberg-Marquardt driven from Python over gtsam's linearisation and sparse solver.

Why not gtsam.LevenbergMarquardtOptimizer.iterate(): when gtsam's C++ optimizer calls a Python
CustomFactor, pybind11 copies the optimizer's (C++-owned) Values into a new Python object for EVERY
call, so each of thousands of line factors pays a copy of all variables: several times slower per
Gauss-Newton iteration than the same linearise + solve + retract + error driven from Python, and growing
quadratically with size (this driver's steps are timed in benchmarks/RESULTS.md, ba_scale). Here the
Values stay Python-owned, so callbacks receive the existing object. The algorithm is gtsam's: damping
lambda * I added as prior factors, lambda divided by `lambda_factor` after an accepted step (not below
`lambda_min`) and multiplied after a rejected one; with `relative_tol` the search for an acceptable step
also ends once the linear model itself promises less than the caller's convergence test asks for, and
with `halve_rejected` a step that raises the cost is first tried at half its length.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import gtsam
import numpy as np


class LevenbergMarquardt:
    """One `iterate()` = one linearisation and as many damped solves as needed to decrease the cost."""

    def __init__(
        self,
        graph: gtsam.NonlinearFactorGraph,
        values: gtsam.Values,
        lambda_initial: float = 1e-4,
        lambda_factor: float = 10.0,
        lambda_max: float = 1e10,
        lambda_min: float = 1e-9,
        error: Callable[[gtsam.Values], float] | None = None,
        relative_tol: float = 0.0,
        halve_rejected: bool = False,
        multifrontal: bool = False,
    ) -> None:
        """`error`: the graph's cost at given values, if there is a faster way than graph.error.
        `relative_tol`: a rejected step whose linear model gains less than this fraction of the cost
        ends the search (see `iterate`); 0 searches until lambda passes its maximum.
        `halve_rejected`: a step that raises the cost is tried again at half its length before the
        damping grows (accepted, the next iteration starts one damping step higher).
        `multifrontal`: eliminate multifrontally (dense fronts: large graphs whose loops fill in),
        else sequentially (a fifth faster on small BA graphs); the same solution either way."""
        self.graph = graph
        self.values = values
        self.cost = error if error is not None else lambda v: float(graph.error(v))
        # lambda = lambda_initial * lambda_factor ** power: an integer power, so that each damping met
        # again is the same float (a cache key), not one drifted by repeated products
        self.lam_initial = lambda_initial
        self.power = 0
        self.factor = lambda_factor
        self.lam_max = lambda_max
        self.lam_min = lambda_min
        self.relative_tol = relative_tol
        self.halve_rejected = halve_rejected
        self.multifrontal = multifrontal
        self.error = self.cost(values)
        self._zero = values.zeroVectors()
        self.keys = list(values.keys())
        self.dims = [len(self._zero.at(k)) for k in self.keys]
        self.ordering: gtsam.Ordering | None = None
        self._damping_cache: dict[float, gtsam.GaussianFactorGraph] = {}
        self.linearize_s = 0.0
        self.solve_s = 0.0
        self.error_s = 0.0
        self.n_linearize = 0
        self.n_solve = 0
        self.n_model_stops = 0
        self.n_halved = 0

    @property
    def lam(self) -> float:
        """The current damping."""
        return self.lam_initial * self.factor**self.power

    def _damping(self, lam: float) -> gtsam.GaussianFactorGraph:
        """The prior factors sqrt(lam) * I on every variable, built once per lambda: lambda moves by
        powers of `lambda_factor` between its bounds, so one problem meets a few tens of values at most,
        each again and again, and building the factors costs about a tenth of a solve."""
        damp = self._damping_cache.get(lam)
        if damp is not None:
            return damp
        damp = gtsam.GaussianFactorGraph()
        s = np.sqrt(lam)
        units = {d: (s * np.eye(d), np.zeros(d), gtsam.noiseModel.Unit.Create(d)) for d in set(self.dims)}
        for key, d in zip(self.keys, self.dims, strict=True):
            damp.push_back(gtsam.JacobianFactor(key, *units[d]))
        self._damping_cache[lam] = damp
        return damp

    def _eliminate(
        self, damped: gtsam.GaussianFactorGraph
    ) -> gtsam.GaussianBayesNet | gtsam.GaussianBayesTree:
        """The damped system eliminated in the chosen order (`multifrontal` or sequential)."""
        if self.multifrontal:
            return damped.eliminateMultifrontal(self.ordering)
        return damped.eliminateSequential(self.ordering)

    def iterate(self) -> bool:
        """Returns True if a step was accepted, False if none is worth searching for: lambda ran past
        its maximum, or a rejected step's linear model already gained less than `relative_tol` of the
        cost. Damping more only shortens the step and lowers that model gain, so no step left to try
        could pass the caller's convergence test (at a minimum, gtsam's rule would otherwise take
        about fourteen more solves, each a full elimination, to reach lambda_max). An indeterminate
        damped system counts as a rejected step, as in gtsam's LM."""
        t = time.perf_counter()
        lin = self.graph.linearize(self.values)
        self.linearize_s += time.perf_counter() - t
        self.n_linearize += 1
        if self.ordering is None:
            self.ordering = gtsam.Ordering.Colamd(gtsam.VariableIndex(lin))
        model_at_zero = lin.error(self._zero) if self.relative_tol > 0 else 0.0
        while True:
            t = time.perf_counter()
            damped = gtsam.GaussianFactorGraph()
            damped.push_back(lin)
            damped.push_back(self._damping(self.lam))
            try:
                delta = self._eliminate(damped).optimize()
            except RuntimeError:  # indeterminate at this damping (as gtsam's LM: damp more)
                delta = None
            self.solve_s += time.perf_counter() - t
            self.n_solve += 1
            new_error = np.inf
            halved = False
            if delta is not None:
                t = time.perf_counter()
                new_values = self.values.retract(delta)
                new_error = self.cost(new_values)
                if self.halve_rejected and not new_error < self.error:
                    # the step overshot: half of it costs one cost evaluation, a re-solve a whole
                    # elimination (the overshoot is mostly a few unanchored lines' curved parameters)
                    new_values = self.values.retract(delta.scale(0.5))
                    new_error = self.cost(new_values)
                    halved = True
                self.error_s += time.perf_counter() - t
            if np.isfinite(new_error) and new_error < self.error:
                self.values, self.error = new_values, new_error
                if halved:  # the model held for half the step only: damp more next time
                    self.power += 1
                    self.n_halved += 1
                elif self.lam / self.factor >= self.lam_min:
                    self.power -= 1
                return True
            if (
                self.relative_tol > 0
                and delta is not None
                and model_at_zero - lin.error(delta) <= self.relative_tol * self.error
            ):
                self.n_model_stops += 1
                return False
            self.power += 1
            if self.lam > self.lam_max:
                return False
