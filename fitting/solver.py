"""Staged nlopt L-BFGS over a :class:`~softras_cl.fitting.params.ParamSet` (docs/fitting.md).

``fit(params, objective, stages)`` runs one ``nlopt.LD_LBFGS`` optimisation per :class:`Stage`,
over that stage's free blocks only (the others stay at their current values). Each stage starts
from the best point of the previous one.

The objective
-------------
``objective(values, stage) -> (loss, grads, terms)``:

- ``values``: dict block name -> float64 array (all blocks; free ones at the point nlopt asks
  for). Do not modify these arrays in place.
- ``stage``: the :class:`Stage` being run. **The solver never renders**: ``stage.sigma`` and
  ``stage.gamma`` (and ``stage.weights``) are data for the objective, which is responsible for
  configuring its rasteriser with them (``None`` means "leave unchanged") and for weighting its
  loss terms (e.g. with ``losses.weighted_sum(terms, stage.weights)``).
- returns ``loss`` (float), ``grads`` (dict block name -> d loss / d value, block-shaped; a free
  block missing from it has gradient zero) and ``terms`` (dict term name -> float, the weighted
  term values, recorded in the history and plotted; may be empty).

Outcomes
--------
Every evaluation with a finite loss is compared with the best so far (L-BFGS also evaluates
line-search points, which may be the lowest ones seen); the best point is what a stage returns,
whatever nlopt returns, and what the next stage starts from.
``FitResult.outcomes[stage.name]`` is the nlopt result name:

- normal returns: ``SUCCESS``, ``STOPVAL_REACHED``, ``FTOL_REACHED``, ``XTOL_REACHED``,
  ``MAXEVAL_REACHED``, ``MAXTIME_REACHED``;
- ``STALLED``: the stage's own convergence stop (``Stage.stall_window``) ended it;
- ``ROUNDOFF_LIMITED`` (``nlopt.RoundoffLimited``): the best point is kept and the fit goes on;
- ``FORCED_STOP`` (``nlopt.ForcedStop``, e.g. raised by the objective to end a stage early);
- generic failures (``FAILURE``, ``INVALID_ARGS``, ``OUT_OF_MEMORY``; nlopt's LD_LBFGS reports
  a line search that cannot make progress, typical of a noisy or inconsistent gradient, as
  ``FAILURE``): the best point is kept and the fit goes on; ``FitError`` only when the stage
  made no finite evaluation at all;
- ``INTERRUPTED``: Ctrl-C / ``KeyboardInterrupt`` (see below).

A NaN or infinite loss, or a non-finite gradient in a free block, raises :class:`FitError`
whose message names the stage, the evaluation and the block(s) whose gradient is not finite
(and the non-finite terms, if any). Any other exception raised by the objective is re-raised
unchanged (after the checkpoint is written). In both cases ``params`` holds the best values of
the last stage that had a finite evaluation.

Ctrl-C
------
A ``KeyboardInterrupt`` raised inside the objective, or a first Ctrl-C anywhere during ``fit``
(in the main thread, when Python's default SIGINT handler is installed; the running evaluation
is allowed to finish), stops the fit: the best values are kept and written to the checkpoint,
and ``fit`` returns normally with ``interrupted=True``. A second Ctrl-C raises at once.

Files (``out_dir``)
-------------------
- ``checkpoint.npz``: the best values so far (one array per block name) plus ``__stage__``
  (stage name), ``__iter__`` (evaluation of that stage at which the best was found), ``__loss__``
  (its loss), ``__evals__`` (evaluations so far, all stages) and ``__completed__`` (stages
  finished). Written atomically (temp file, then ``os.replace``) when the best improves, at most
  every ``CHECKPOINT_INTERVAL`` seconds, and always at the end of each stage, on interruption
  and before raising. Read it with :func:`load_checkpoint` or ``np.load``.
- ``history.json``: ``{"stages": [...], "outcomes": {...}, "interrupted": bool, "history": [...]}``
  where each history entry is ``{"stage", "iter", "loss", "terms"}``, one per evaluation.
- ``loss_curve.png``: total loss and each term against the evaluation index, log y axis, stage
  boundaries marked.

Resuming
--------
``fit(..., out_dir=DIR, resume=True)`` continues the fit whose checkpoint.npz is in DIR: the
values start from the checkpoint (which must hold exactly the blocks and shapes of ``params``),
the stages it finished are skipped (their history and outcomes are read back from
history.json), and the stage it was in runs again from its best point, with its full budget.

A tqdm bar on stderr shows the stage, evaluation and loss (``progress=False`` disables it).
"""
from __future__ import annotations

import json
import math
import os
import sys
import time
import zipfile
import zlib
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import nlopt
import numpy as np

from softras_cl.fitting.params import ParamSet
from softras_cl.errors import InputError, ResultError
from softras_cl.interrupts import first_interrupt_calls
from softras_cl.io.images import PNG_OPTIONS
from softras_cl.io.outputs import atomic_path, write_bytes, write_figure

__all__ = ["Stage", "FitResult", "FitError", "Objective", "fit", "load_checkpoint",
           "CHECKPOINT_INTERVAL", "MIN_DEPTH", "TOO_CLOSE_LOSS", "too_close_result"]

CHECKPOINT_INTERVAL = 0.5       # seconds between two checkpoint writes during a stage
# A model placed nearer the camera than MIN_DEPTH metres, or behind it, cannot be projected. An
# objective answers such a point with too_close_result() (TOO_CLOSE_LOSS, more than any model in
# view scores, and no gradient), so that the line search steps back instead of the fit stopping with
# "vertices are behind the camera": a long step from a poor start can land there.
MIN_DEPTH = 0.01
TOO_CLOSE_LOSS = 1e12
_META_KEYS = ("__stage__", "__iter__", "__loss__", "__evals__", "__completed__")

_RESULT_NAMES = {getattr(nlopt, n): n for n in (
    "SUCCESS", "STOPVAL_REACHED", "FTOL_REACHED", "XTOL_REACHED", "MAXEVAL_REACHED",
    "MAXTIME_REACHED", "FAILURE", "INVALID_ARGS", "OUT_OF_MEMORY", "ROUNDOFF_LIMITED",
    "FORCED_STOP") if hasattr(nlopt, n)}


@dataclass
class Stage:
    """One optimisation stage, given as data.

    name:     unique among the stages of a fit (keys ``FitResult.outcomes``).
    free:     blocks optimised in this stage (a single name is accepted too).
    weights:  loss-term weights by name, for the objective to apply.
    sigma, gamma: rasteriser sharpness for this stage, for the objective to apply (None: leave
              the rasteriser as it is). The solver itself never renders.
    max_iters: nlopt ``maxeval``, i.e. objective evaluations (line-search points included); a
              hard cap (nlopt's L-BFGS can overshoot maxeval inside a line search; the solver
              stops it at the cap and reports MAXEVAL_REACHED).
    ftol_rel, xtol_rel: nlopt relative tolerances (x in scaled units, see params.py).
    stall_window, stall_rel: the solver's own convergence stop (0 disables it, the default):
              the stage ends (outcome ``STALLED``) at the first evaluation k > stall_window
              where the best loss improved by at most ``stall_rel * |best|`` over the last
              stall_window evaluations: ``best(k - stall_window) - best(k) <= stall_rel *
              |best(k)|`` (best(j): the lowest loss of the stage's first j evaluations). Unlike nlopt's ftol_rel, which compares two successive iterates,
              the window sees through L-BFGS's line searches and its slow, noisy tails. The
              budget (max_iters) stays the cap.
    """
    name: str
    free: tuple[str, ...]
    weights: dict = field(default_factory=dict)
    sigma: float | None = None
    gamma: float | None = None
    max_iters: int = 100
    ftol_rel: float = 1e-7
    xtol_rel: float = 1e-9
    stall_window: int = 0
    stall_rel: float = 0.0

    def __post_init__(self):
        if isinstance(self.free, str):
            self.free = (self.free,)
        self.free = tuple(self.free)


Objective = Callable[[dict, Stage], "tuple[float, dict, dict]"]


def too_close_result() -> tuple[float, dict, dict]:
    """An objective's (loss, grads, terms) for a point that puts the model too close to the camera
    (MIN_DEPTH): TOO_CLOSE_LOSS, no gradient; new dicts each time."""
    return TOO_CLOSE_LOSS, {}, {"too_close": TOO_CLOSE_LOSS}


@dataclass
class FitResult:
    """values: best values (all blocks) at the end; loss: their loss in the last stage that made
    a finite evaluation; history: one dict(stage, iter, loss, terms) per evaluation; outcomes:
    stage name -> nlopt result name (stages never started are absent); interrupted: Ctrl-C."""
    values: dict
    loss: float
    history: list
    outcomes: dict
    interrupted: bool = False


class FitError(ResultError):
    """A fit cannot go on: non-finite loss or gradient, or an nlopt failure with no finite
    evaluation. ``stage``: stage name; ``blocks``: blocks with a non-finite gradient (may be
    empty); ``iter``: evaluation within the stage (None when not tied to one)."""

    def __init__(self, message, stage=None, blocks=(), iter=None):
        super().__init__(message)
        self.stage, self.blocks, self.iter = stage, tuple(blocks), iter


def load_checkpoint(path) -> tuple[dict, dict]:
    """Read ``checkpoint.npz`` -> (values: name -> array, meta: dict(stage, iter, loss, evals,
    completed)); ``completed`` (stages finished) is 0 in checkpoints that predate it.
    InputError naming the file when it cannot be read or is corrupt (truncated, not an .npz,
    metadata missing)."""
    try:
        with np.load(path, allow_pickle=False) as z:
            values = {k: np.array(z[k]) for k in z.files if k not in _META_KEYS}
            meta = {"stage": str(z["__stage__"]), "iter": int(z["__iter__"]),
                    "loss": float(z["__loss__"]), "evals": int(z["__evals__"]),
                    "completed": int(z["__completed__"]) if "__completed__" in z.files else 0}
    except OSError as e:
        raise InputError(f"cannot read checkpoint {path}: {e}") from e
    except (zipfile.BadZipFile, zlib.error, EOFError, ValueError, KeyError) as e:
        raise InputError(f"checkpoint {path} is corrupt ({_what_is_wrong(e)}); it cannot be resumed: "
                         f"start the fit again without --resume (that replaces it)") from e
    return values, meta


def _what_is_wrong(error: Exception) -> str:
    """What np.load's ``error`` says about a checkpoint file, in a few words."""
    if isinstance(error, KeyError):
        return f"no {error.args[0].split()[0]} entry: not the checkpoint of a fit"
    if isinstance(error, ValueError):
        return "not an .npz archive"
    return f"truncated or damaged: {type(error).__name__}: {error}"


def _new_opt(n: int):
    """The optimiser of one stage (a function so tests can substitute it)."""
    return nlopt.opt(nlopt.LD_LBFGS, n)


def _float_or_none(v):
    return float(v) if math.isfinite(v) else None


class _State:
    def __init__(self):
        self.interrupt = False
        self.opt = None


class _Fit:
    def __init__(self, params, objective, stages, out_dir, progress):
        self.params, self.objective, self.stages = params, objective, stages
        self.out = Path(out_dir) if out_dir is not None else None
        self.history: list[dict] = []
        self.outcomes: dict[str, str] = {}
        self.boundaries: list[tuple[int, str]] = []   # (first evaluation index, stage name)
        self.state = _State()
        self.evals = 0
        self.last_write = -math.inf
        self.current = params.values()        # best values so far (start of the next stage)
        self.current_loss = math.inf
        self.ckpt_meta = ("", 0, math.inf)    # (stage, iter, loss) of self.current
        self.completed = 0                    # stages finished (the next one to run)
        self.bar = None
        self.progress = progress

    # ---- files -----------------------------------------------------------------------------
    def write_checkpoint(self, values, stage, it, loss):
        if self.out is None:
            return
        arrays = {k: np.asarray(v, dtype=np.float64) for k, v in values.items()}
        arrays.update(__stage__=np.array(stage), __iter__=np.array(it, dtype=np.int64),
                      __loss__=np.array(loss, dtype=np.float64),
                      __evals__=np.array(self.evals, dtype=np.int64),
                      __completed__=np.array(self.completed, dtype=np.int64))
        with atomic_path(self.out / "checkpoint.npz") as tmp:
            np.savez(tmp, **arrays)
        self.last_write = time.monotonic()

    def write_history(self, interrupted):
        if self.out is None:
            return
        doc = {
            "stages": [{**asdict(s), "free": list(s.free)} for s in self.stages],
            "outcomes": self.outcomes,
            "interrupted": interrupted,
            "history": [{"stage": h["stage"], "iter": h["iter"], "loss": _float_or_none(h["loss"]),
                         "terms": {k: _float_or_none(v) for k, v in h["terms"].items()}}
                        for h in self.history],
        }
        # one line per history entry: readable, and small for long fits
        head = json.dumps({k: v for k, v in doc.items() if k != "history"}, indent=1, default=str)
        rows = ",\n".join("  " + json.dumps(h, default=str) for h in doc["history"])
        text = (head[:-2] + ',\n "history": [\n' + rows + "\n ]\n}\n").encode()
        write_bytes(self.out / "history.json", text)

    def write_plot(self):
        if self.out is None:
            return
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure

        fig = Figure(figsize=(8, 4.5), dpi=100)
        FigureCanvasAgg(fig)
        ax = fig.add_subplot(1, 1, 1)
        n = len(self.history)
        xs = np.arange(1, n + 1)
        series = {"total": np.array([h["loss"] for h in self.history], dtype=np.float64)}
        names = []
        for h in self.history:
            for k in h["terms"]:
                if k not in names:
                    names.append(k)
        for k in names:
            series[k] = np.array([h["terms"].get(k, np.nan) for h in self.history], dtype=np.float64)
        allv = np.concatenate([v[np.isfinite(v)] for v in series.values()]) if n else np.zeros(0)
        negative = bool(np.any(allv < 0))
        for k, v in series.items():
            if not n:
                continue
            if not negative:                 # log axis: zeros cannot be drawn, leave gaps
                v = np.where(v > 0, v, np.nan)
            ax.plot(xs, v, lw=2.0 if k == "total" else 1.0,
                    color="k" if k == "total" else None, label=k)
        if n:                                # running best of the total within each stage
            run = series["total"].copy()
            for i in range(1, n):
                if self.history[i]["stage"] == self.history[i - 1]["stage"]:
                    run[i] = min(run[i], run[i - 1])
            ax.plot(xs, run if negative else np.where(run > 0, run, np.nan), color="k", lw=1.0,
                    ls=":", label="best in stage")
        if negative:
            ax.set_yscale("symlog", linthresh=max(1e-12, 1e-3 * float(np.max(np.abs(allv)))))
        elif np.any(allv > 0):
            ax.set_yscale("log")
        for first, name in self.boundaries:
            ax.axvline(first - 0.5, color="0.6", ls="--", lw=0.8)
            ax.text(first - 0.5, 1.01, name, transform=ax.get_xaxis_transform(), va="bottom",
                    ha="left", fontsize=8, color="0.3", rotation=30, clip_on=False)
        ax.set_xlabel("evaluation")
        ax.set_ylabel("loss (weighted terms)")
        ax.grid(True, which="both", alpha=0.3)
        if n:
            ax.legend(fontsize=8, loc="upper right")
        # fixed margins, not tight_layout: its layout pass measures every tick label, which cost
        # more than drawing the plot; these leave room for log-axis labels and the stage names
        fig.subplots_adjust(left=0.1, right=0.98, bottom=0.11, top=0.88)
        write_figure(fig, self.out / "loss_curve.png", **PNG_OPTIONS)

    def write_all(self, interrupted):
        self.write_checkpoint(self.current, *self.ckpt_meta)
        self.write_history(interrupted)
        self.write_plot()

    def stop_at_next_evaluation(self, signum):
        """The first Ctrl-C/SIGTERM: nlopt stops after the running evaluation (raising inside
        nlopt's callback would be swallowed by nlopt); the best values are kept."""
        self.state.interrupt = True
        if self.state.opt is not None:
            self.state.opt.force_stop()

    # ---- one stage -------------------------------------------------------------------------
    def run_stage(self, stage: Stage):
        """One nlopt run over the stage's free blocks; the stage's best point becomes
        ``self.current``. Raises the objective's error, or FitError when nlopt failed before any
        finite evaluation (both after writing the files)."""
        self.boundaries.append((len(self.history) + 1, stage.name))
        free = self.params._free(stage.free)
        x0 = self.params.pack(self.current, free)
        bounds = self.params.bounds(free)
        opt = _new_opt(x0.size)
        self.state.opt = opt
        objective = _StageObjective(self, stage, opt)
        try:
            outcome, error = self._optimize(opt, stage, objective, x0, bounds)
        finally:
            self.state.opt = None
        self.outcomes[stage.name] = objective.outcome(outcome)
        self._keep_best(objective)
        if self.bar is not None:      # keep the bar's total consistent with an early stop
            self.bar.update(max(0, int(stage.max_iters) - objective.evals))
        self._end_stage(stage, objective, error)

    def _optimize(self, opt, stage: Stage, objective, x0, bounds) -> tuple[str | None, Exception | None]:
        """Run nlopt from x0 (scaled free values) within bounds (lower, upper) -> (nlopt's
        result name, or None on Ctrl-C; the exception of a generic nlopt failure, else None)."""
        try:
            opt.set_lower_bounds(bounds[0])
            opt.set_upper_bounds(bounds[1])
            opt.set_min_objective(objective)
            opt.set_maxeval(int(stage.max_iters))
            opt.set_ftol_rel(float(stage.ftol_rel))
            opt.set_xtol_rel(float(stage.xtol_rel))
            opt.optimize(x0)
            code = opt.last_optimize_result()
            return _RESULT_NAMES.get(code, str(code)), None
        except nlopt.RoundoffLimited:
            return "ROUNDOFF_LIMITED", None
        except nlopt.ForcedStop:
            return "FORCED_STOP", None
        except KeyboardInterrupt:
            self.state.interrupt = True
            return None, None
        except MemoryError as exc:
            return "OUT_OF_MEMORY", exc
        except ValueError as exc:
            return "INVALID_ARGS", exc
        except Exception as exc:            # nlopt's runtime_error / RuntimeError: FAILURE
            return "FAILURE", exc

    def _keep_best(self, objective: "_StageObjective") -> None:
        """Carry the stage's best point on, whatever happened."""
        if objective.best_values is None:
            return
        self.current = {**objective.base, **objective.best_values}
        self.current_loss = objective.best_loss
        self.ckpt_meta = (objective.stage.name, objective.best_iter, objective.best_loss)
        self.params.set(objective.best_values)

    def _end_stage(self, stage: Stage, objective: "_StageObjective", error) -> None:
        """Re-raise what stopped the stage, or count it finished; write the checkpoint."""
        if objective.errors:
            self.write_all(False)
            raise objective.errors[0]
        if objective.forced_stop:
            self.outcomes[stage.name] = "FORCED_STOP"
        if error is not None and objective.best_values is None and not self.state.interrupt:
            self.write_all(False)
            raise FitError(f"stage {stage.name!r}: nlopt stopped with {self.outcomes[stage.name]} "
                           f"({type(error).__name__}: {error}) before any finite evaluation",
                           stage=stage.name) from error
        if not self.state.interrupt:
            self.completed += 1
        self.write_checkpoint(self.current, *self.ckpt_meta)

    # ---- resuming --------------------------------------------------------------------------
    def resume(self) -> None:
        """Start from out/checkpoint.npz: its values, the stages it finished skipped, their
        history and outcomes read back from history.json. InputError when it does not fit."""
        path = self.out / "checkpoint.npz"
        if not path.is_file():
            raise InputError(f"cannot resume: {path} does not exist (no fit was started there)")
        values, meta = load_checkpoint(path)
        expected = {n: self.params.shape(n) for n in self.params.names}
        found = {n: tuple(v.shape) for n, v in values.items()}
        names = [st.name for st in self.stages]
        if found != expected or meta["completed"] > len(names) or meta["stage"] not in names + [""]:
            raise InputError(f"cannot resume from {path}: it is the checkpoint of another fit "
                             f"(blocks {found}, stage {meta['stage']!r}); this fit has blocks "
                             f"{expected} and stages {names}")
        try:
            self.params.set(values)
        except ValueError as e:
            raise InputError(f"cannot resume from {path}: {e}") from e
        self.current, self.current_loss = self.params.values(), meta["loss"]
        self.ckpt_meta = (meta["stage"], meta["iter"], meta["loss"])
        self.completed, self.evals = meta["completed"], meta["evals"]
        self._read_back_history(set(names[:self.completed]))

    def _read_back_history(self, finished: set) -> None:
        """History entries and outcomes of the ``finished`` stages from history.json, if any."""
        try:
            doc = json.loads((self.out / "history.json").read_text())
        except (OSError, ValueError):
            return
        for h in doc.get("history", []):
            if h.get("stage") in finished:
                if not self.history or self.history[-1]["stage"] != h["stage"]:
                    self.boundaries.append((len(self.history) + 1, h["stage"]))
                loss = math.nan if h.get("loss") is None else float(h["loss"])
                terms = {k: math.nan if v is None else float(v) for k, v in h.get("terms", {}).items()}
                self.history.append({"stage": h["stage"], "iter": h["iter"], "loss": loss, "terms": terms})
        self.outcomes.update({k: v for k, v in doc.get("outcomes", {}).items() if k in finished})

    def run(self) -> FitResult:
        from tqdm import tqdm
        remaining = self.stages[self.completed:]
        total = sum(int(s.max_iters) for s in remaining)
        self.bar = tqdm(total=total, file=sys.stderr, disable=not self.progress, leave=True,
                        dynamic_ncols=True, unit="eval")
        if self.bar.disable:
            self.bar = None
        try:
            with first_interrupt_calls(self.stop_at_next_evaluation):
                for stage in remaining:
                    if self.state.interrupt:
                        break
                    self.run_stage(stage)
        finally:
            if self.bar is not None:
                self.bar.close()
        self.write_all(self.state.interrupt)
        return FitResult(values={k: np.array(v, copy=True) for k, v in self.current.items()},
                         loss=self.current_loss, history=self.history, outcomes=dict(self.outcomes),
                         interrupted=self.state.interrupt)


class _StageObjective:
    """nlopt's objective function for one stage: ``(x, grad) -> loss``.

    Each call evaluates the fit's objective at x (scaled, free blocks only), checks the loss and
    gradient are finite, records the evaluation in the history, keeps the best point (and
    checkpoints it), and stops nlopt (``force_stop``) at the stage's budget, at a stall, on
    Ctrl-C, or when the objective raised. Nothing may escape to nlopt's wrapper, which would
    turn any exception into a bare ForcedStop and lose its cause: errors are kept in ``errors``
    for the stage to re-raise, an nlopt.ForcedStop from the objective sets ``forced_stop``.
    """

    def __init__(self, run: _Fit, stage: Stage, opt):
        self.run, self.stage, self.opt = run, stage, opt
        self.params = run.params
        self.free = self.params._free(stage.free)
        self.base = run.current                 # values of the blocks this stage leaves alone
        self.budget = int(stage.max_iters)
        self.evals = 0                          # evaluations of this stage
        self.best_loss, self.best_iter, self.best_values = math.inf, 0, None
        self.bests = [math.inf]                 # bests[j]: lowest loss of the first j evaluations
        self.over_budget = False                # nlopt may overshoot maxeval inside a line search
        self.stalled = False                    # Stage.stall_window's stop
        self.forced_stop = False                # the objective raised nlopt.ForcedStop
        self.errors: list[BaseException] = []   # FitError or a bug in the objective

    def __call__(self, x, grad) -> float:
        try:
            if self.evals >= self.budget:
                self.over_budget = True
            if (self.errors or self.forced_stop or self.run.state.interrupt or self.over_budget
                    or self.stalled):
                return self.stop(grad)
            return self.evaluate(x, grad)
        except nlopt.ForcedStop:
            self.forced_stop = True
        except KeyboardInterrupt:
            self.run.state.interrupt = True
        except BaseException as exc:
            self.errors.append(exc)
        return self.stop(grad)

    def stop(self, grad) -> float:
        """Ask nlopt to stop; a zero gradient and the best loss so far for this call."""
        self.opt.force_stop()
        if grad.size:
            grad[:] = 0.0
        return self.best_loss if math.isfinite(self.best_loss) else 0.0

    def evaluate(self, x, grad) -> float:
        """The objective at x: loss returned, its gradient written into ``grad``."""
        self.evals += 1
        self.run.evals += 1
        values = self.params.unpack(x, self.free, self.base)
        loss, grads, terms = self.run.objective(values, self.stage)
        grads = {} if grads is None else grads
        terms = {} if terms is None else {str(t): float(v) for t, v in dict(terms).items()}
        loss = float(loss)
        g = self.params.pack_grad(grads, self.free)
        self.check_finite(loss, g, terms)
        self.run.history.append({"stage": self.stage.name, "iter": self.evals, "loss": loss,
                                 "terms": terms})
        self.keep_if_best(loss, values)
        self.show(loss)
        if grad.size:
            grad[:] = g
        return loss

    def check_finite(self, loss: float, g, terms: dict) -> None:
        """FitError naming the stage, the evaluation, the blocks whose gradient is not finite
        and the non-finite terms, when the loss or a free block's gradient is not finite."""
        bad_blocks = [n for n, sl in self.params.slices(self.free).items()
                      if not np.all(np.isfinite(g[sl]))]
        if math.isfinite(loss) and not bad_blocks:
            return
        bad_terms = [t for t, v in terms.items() if not math.isfinite(v)]
        msg = (f"stage {self.stage.name!r}, evaluation {self.evals}: "
               + (f"loss is {loss}" if not math.isfinite(loss) else "loss is finite")
               + "; " + (f"gradient not finite in block(s) "
                         f"{', '.join(repr(b) for b in bad_blocks)}" if bad_blocks
                         else "gradients of all free blocks are finite")
               + (f"; non-finite term(s): {', '.join(bad_terms)}" if bad_terms else ""))
        raise FitError(msg, stage=self.stage.name, blocks=bad_blocks, iter=self.evals)

    def keep_if_best(self, loss: float, values: dict) -> None:
        """Keep (and checkpoint, at most every CHECKPOINT_INTERVAL) a new best point; stop
        nlopt when the stage has stalled."""
        if loss < self.best_loss:
            self.best_loss, self.best_iter = loss, self.evals
            self.best_values = {n: values[n].copy() for n in self.free}
            if time.monotonic() - self.run.last_write >= CHECKPOINT_INTERVAL:
                self.run.write_checkpoint({**self.base, **self.best_values}, self.stage.name,
                                          self.evals, loss)
        self.bests.append(self.best_loss)
        if _stalled(self.stage, self.bests):
            self.stalled = True
            self.opt.force_stop()

    def show(self, loss: float) -> None:
        """Advance the progress bar, if any."""
        bar = self.run.bar
        if bar is not None:
            bar.set_description(self.stage.name, refresh=False)
            bar.set_postfix(iter=self.evals, loss=f"{loss:.6g}", best=f"{self.best_loss:.6g}",
                            refresh=False)
            bar.update(1)

    def outcome(self, nlopt_outcome: str | None) -> str | None:
        """The stage's outcome: INTERRUPTED on Ctrl-C, STALLED or MAXEVAL_REACHED when the
        solver's own stop ended it, else what nlopt returned."""
        if self.run.state.interrupt:
            return "INTERRUPTED"
        if (nlopt_outcome == "FORCED_STOP" and not self.errors and not self.forced_stop
                and (self.over_budget or self.stalled)):
            return "STALLED" if self.stalled else "MAXEVAL_REACHED"
        return nlopt_outcome


def _stalled(stage: Stage, bests: list) -> bool:
    """Stage.stall_window's test on bests[j], the best loss after j evaluations."""
    w = int(stage.stall_window)
    if w < 1 or len(bests) <= w:
        return False
    return bests[-1 - w] - bests[-1] <= stage.stall_rel * abs(bests[-1])


def _check_stages(params: ParamSet, stages) -> list[Stage]:
    stages = list(stages)
    if not stages:
        raise ValueError("fit needs at least one stage")
    seen = set()
    for s in stages:
        if not isinstance(s, Stage):
            raise ValueError(f"stages must be Stage objects, got {type(s).__name__}")
        if not isinstance(s.name, str) or not s.name:
            raise ValueError(f"stage name must be a non-empty string, got {s.name!r}")
        if s.name in seen:
            raise ValueError(f"duplicate stage name {s.name!r}")
        seen.add(s.name)
        if not s.free:
            raise ValueError(f"stage {s.name!r}: no free blocks")
        try:
            params._free(s.free)
        except ValueError as exc:
            raise ValueError(f"stage {s.name!r}: {exc}") from None
        if int(s.max_iters) < 1:
            raise ValueError(f"stage {s.name!r}: max_iters must be >= 1")
        if not (s.ftol_rel >= 0 and s.xtol_rel >= 0 and s.stall_rel >= 0):
            raise ValueError(f"stage {s.name!r}: ftol_rel, xtol_rel and stall_rel must be >= 0")
        if isinstance(s.stall_window, bool) or not isinstance(s.stall_window, int) or s.stall_window < 0:
            raise ValueError(f"stage {s.name!r}: stall_window must be an integer >= 0 (evaluations; "
                             f"0: no convergence stop), got {s.stall_window!r}")
    return stages


def fit(params: ParamSet, objective: Objective, stages: Sequence[Stage], out_dir=None,
        progress: bool = True, resume: bool = False) -> FitResult:
    """Run the stages in order from ``params``' current values; see the module docstring.
    ``resume`` (needs ``out_dir``) continues from the checkpoint.npz there (see "Resuming").

    On return (and on interruption) ``params`` holds the best values found, and so does
    ``FitResult.values``.
    """
    if not isinstance(params, ParamSet):
        raise ValueError(f"params must be a ParamSet, got {type(params).__name__}")
    if not callable(objective):
        raise ValueError("objective must be callable")
    stages = _check_stages(params, stages)
    clash = [n for n in params.names if n in _META_KEYS]
    if clash:
        raise ValueError(f"block name(s) {clash} are reserved for checkpoint metadata")
    if resume and out_dir is None:
        raise ValueError("resume=True needs out_dir (the folder holding checkpoint.npz)")
    if out_dir is not None:
        os.makedirs(out_dir, exist_ok=True)
    run = _Fit(params, objective, stages, out_dir, progress)
    if resume:
        run.resume()
    return run.run()
