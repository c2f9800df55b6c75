"""fitting/solver.py (docs/fitting.md): staged nlopt L-BFGS on smooth problems with known
answers, the stage schedule as the objective sees it, best-point tracking, every nlopt outcome,
non-finite losses/gradients, Ctrl-C and the files written to out_dir."""
import dataclasses
import json
import os
import signal
import threading

import nlopt
import numpy as np
import pytest

from softras_cl.errors import InputError
from softras_cl.fitting import solver as solver_module
from softras_cl.fitting.params import Block, ParamSet
from softras_cl.fitting.solver import FitError, FitResult, Stage, fit, load_checkpoint

# Two blocks of very different magnitudes; the scales make them O(1) for the optimiser.
SA, SB = 1e-3, 1e3
A_STAR = np.array([1.5, -0.5, 2.0]) * SA
B_STAR = np.array([[0.3, -1.2], [0.7, 2.5]]) * SB


def quad_params():
    return ParamSet([Block("a", np.zeros(3), scale=SA),
                     Block("b", np.ones((2, 2)) * SB, lower=-5 * SB, upper=5 * SB, scale=SB)])


class Quadratic:
    """Shifted quadratic in scaled units, separable between the blocks; records what it sees."""

    def __init__(self):
        self.seen = []          # (stage object, sigma, gamma, copies of the values, loss)

    def __call__(self, values, stage):
        da = (values["a"] - A_STAR) / SA
        db = (values["b"] - B_STAR) / SB
        ta = stage.weights.get("a", 1.0) * float(np.sum(da ** 2))
        tb = stage.weights.get("b", 1.0) * float(np.sum(db ** 2))
        loss = ta + tb
        self.seen.append((stage, stage.sigma, stage.gamma,
                          {k: v.copy() for k, v in values.items()}, loss))
        grads = {"a": stage.weights.get("a", 1.0) * 2 * da / SA,
                 "b": stage.weights.get("b", 1.0) * 2 * db / SB}
        return loss, grads, {"a": ta, "b": tb}


def test_two_stages_recover_the_known_answer_and_follow_the_schedule():
    params = quad_params()
    b0 = params.values()["b"].copy()
    stages = [Stage("coarse", ("a",), {"a": 1.0, "b": 1.0}, sigma=1e-4, gamma=1e-4, max_iters=60),
              Stage("fine", ("b",), {"a": 1.0, "b": 2.0}, sigma=1e-5, gamma=3e-5, max_iters=60)]
    obj = Quadratic()
    res = fit(params, obj, stages, progress=False)
    assert isinstance(res, FitResult) and not res.interrupted
    np.testing.assert_allclose(res.values["a"], A_STAR, rtol=1e-6, atol=1e-6 * SA)
    np.testing.assert_allclose(res.values["b"], B_STAR, rtol=1e-6, atol=1e-6 * SB)
    assert res.loss < 1e-10
    assert set(res.outcomes) == {"coarse", "fine"}
    assert all(o in {"SUCCESS", "FTOL_REACHED", "XTOL_REACHED"} for o in res.outcomes.values())

    # The schedule as the objective saw it: stage objects, sigma/gamma, in order, never mixed.
    names = [s.name for s, *_ in obj.seen]
    k = names.index("fine")
    assert names[:k] == ["coarse"] * k and names[k:] == ["fine"] * (len(names) - k)
    assert all(s is stages[0] and (sg, gm) == (1e-4, 1e-4) for s, sg, gm, *_ in obj.seen[:k])
    assert all(s is stages[1] and (sg, gm) == (1e-5, 3e-5) for s, sg, gm, *_ in obj.seen[k:])
    # Which blocks moved: only a in "coarse" (b frozen at its start), only b in "fine" (a frozen
    # at the best point of "coarse").
    assert all(np.array_equal(v["b"], b0) for _, _, _, v, _ in obj.seen[:k])
    assert len({v["a"].tobytes() for _, _, _, v, _ in obj.seen[:k]}) > 1
    a_carried = obj.seen[k][3]["a"]
    assert all(np.array_equal(v["a"], a_carried) for _, _, _, v, _ in obj.seen[k:])
    best_coarse = min(obj.seen[:k], key=lambda s: s[4])[3]["a"]
    np.testing.assert_array_equal(a_carried, best_coarse)

    # History: one entry per evaluation, iter counting within each stage.
    assert len(res.history) == len(obj.seen)
    assert [h["iter"] for h in res.history[:k]] == list(range(1, k + 1))
    assert res.history[k]["stage"] == "fine" and res.history[k]["iter"] == 1
    assert set(res.history[0]) == {"stage", "iter", "loss", "terms"}
    assert set(res.history[0]["terms"]) == {"a", "b"}
    # params now holds the best values
    np.testing.assert_array_equal(params.values()["b"], res.values["b"])


SX, SY = 0.01, 1000.0


def rosen_params(x0=-1.2, y0=1.0):
    return ParamSet([Block("x", np.array([x0 * SX]), scale=SX), Block("y", np.array(y0 * SY), scale=SY)])


def rosen(values, stage):
    """Rosenbrock in (x / SX, y / SY): minimum 0 at x = SX, y = SY; needs dozens of evaluations."""
    x, y = float(values["x"][0]) / SX, float(values["y"]) / SY
    r = y - x * x
    f = (1 - x) ** 2 + 100 * r * r
    grads = {"x": np.array([(-2 * (1 - x) - 400 * x * r) / SX]), "y": np.array(200 * r / SY)}
    return f, grads, {"valley": 100 * r * r, "line": (1 - x) ** 2}


def test_rosenbrock_across_blocks_with_different_scales():
    res = fit(rosen_params(), rosen, [Stage("y only", ("y",), max_iters=50),
                                      Stage("both", ("x", "y"), max_iters=500, ftol_rel=1e-15,
                                            xtol_rel=1e-12)],
              progress=False)
    np.testing.assert_allclose(res.values["x"], [SX], rtol=1e-5)
    np.testing.assert_allclose(res.values["y"], SY, rtol=1e-5)
    assert len([h for h in res.history if h["stage"] == "both"]) > 20
    # stage 1 (x frozen at -1.2) minimises over y alone: y = x^2
    first = [h for h in res.history if h["stage"] == "y only"]
    assert min(h["loss"] for h in first) == pytest.approx(2.2 ** 2, rel=1e-8)


def test_max_iters_is_a_hard_cap_on_evaluations():
    """nlopt's L-BFGS overshoots maxeval inside a line search from this start; the cap holds."""
    res = fit(rosen_params(), rosen, [Stage("capped", ("x", "y"), max_iters=8),
                                      Stage("next", ("y",), max_iters=3)], progress=False)
    assert res.outcomes["capped"] == "MAXEVAL_REACHED"
    assert [h["stage"] for h in res.history] == ["capped"] * 8 + ["next"] * 3


def noisy_objective(seed):
    rng = np.random.default_rng(seed)
    seen = []

    def obj(values, stage):
        a = values["a"]
        f = float(np.sum((a - 0.3) ** 2)) + 1e-6 * rng.normal()
        seen.append((f, a.copy()))
        return f, {"a": 2 * (a - 0.3) + 1e-3 * rng.normal(size=a.shape)}, {}
    return obj, seen


def test_noisy_objective_failure_keeps_the_best_point():
    """A noisy gradient makes nlopt's L-BFGS line search fail (nlopt reports FAILURE for it):
    the fit goes on and returns the lowest point evaluated, not nlopt's last one."""
    obj, seen = noisy_objective(0)
    params = ParamSet([Block("a", np.array([1.0, 2.0]))])
    res = fit(params, obj, [Stage("noisy", ("a",), max_iters=200, ftol_rel=0, xtol_rel=0),
                            Stage("after", ("a",), max_iters=3)], progress=False)
    assert res.outcomes["noisy"] == "FAILURE"
    assert "after" in res.outcomes                       # the next stage still ran
    stage1 = seen[:len([h for h in res.history if h["stage"] == "noisy"])]
    best_f, best_a = min(stage1, key=lambda s: s[0])
    assert stage1[-1][0] > best_f                        # the last point was not the best
    # stage "after" starts from the best of "noisy"
    np.testing.assert_array_equal(seen[len(stage1)][1], best_a)
    np.testing.assert_allclose(res.values["a"], 0.3, atol=1e-2)


class FakeOpt:
    """Stands in for nlopt.opt: evaluates the given points, then raises `exc` (LD_LBFGS itself
    never returns ROUNDOFF_LIMITED, so that outcome has to be forced this way)."""

    def __init__(self, n, points, exc):
        self.n, self.points, self.exc = n, points, exc

    def set_lower_bounds(self, lo): pass
    def set_upper_bounds(self, hi): pass
    def set_maxeval(self, n): pass
    def set_ftol_rel(self, t): pass
    def set_xtol_rel(self, t): pass
    def force_stop(self): pass
    def set_min_objective(self, f): self.f = f
    def last_optimize_result(self): return nlopt.FAILURE

    def optimize(self, x0):
        for p in self.points:
            self.f(np.asarray(p, float), np.zeros(self.n))
        raise self.exc


def fake_first_stage(monkeypatch, points, exc):
    real, calls = solver_module._new_opt, []

    def new_opt(n):
        calls.append(n)
        return FakeOpt(n, points, exc) if len(calls) == 1 else real(n)
    monkeypatch.setattr(solver_module, "_new_opt", new_opt)


def test_roundoff_limited_keeps_the_best_point_and_continues(monkeypatch, tmp_path):
    fake_first_stage(monkeypatch, [[3.0, 3.0], [0.5, 0.2], [2.0, -1.0]],
                     nlopt.RoundoffLimited("roundoff"))
    obj = Quadratic()
    params = ParamSet([Block("a", np.zeros(2), scale=SA), Block("b", np.zeros(()), scale=SB)])
    star = np.array([0.5, 0.2]) * SA

    def f(values, stage):
        d = (values["a"] - star) / SA
        loss = float(np.sum(d ** 2))
        obj.seen.append((stage, None, None, {k: v.copy() for k, v in values.items()}, loss))
        return loss, {"a": 2 * d / SA}, {}

    res = fit(params, f, [Stage("s1", ("a",), max_iters=10), Stage("s2", ("a",), max_iters=2)],
              out_dir=tmp_path, progress=False)
    assert res.outcomes["s1"] == "ROUNDOFF_LIMITED"
    assert "s2" in res.outcomes and not res.interrupted
    # s1's best was its second point, which is s2's starting point
    assert [h["loss"] for h in res.history[:3]][1] == 0.0
    np.testing.assert_allclose(obj.seen[3][3]["a"], star)
    np.testing.assert_allclose(res.values["a"], star)
    assert res.loss == 0.0


def test_generic_failure_keeps_best_or_raises_without_a_finite_evaluation(monkeypatch):
    fake_first_stage(monkeypatch, [[1.0], [0.1]], RuntimeError("nlopt failure"))
    params = ParamSet([Block("a", np.zeros(1))])
    obj = lambda v, s: (float(v["a"][0] ** 2), {"a": 2 * v["a"]}, {})
    res = fit(params, obj, [Stage("s1", "a"), Stage("s2", "a", max_iters=1)], progress=False)
    assert res.outcomes["s1"] == "FAILURE"
    assert res.history[2]["stage"] == "s2"
    np.testing.assert_allclose(res.values["a"], [0.1])    # s2's one evaluation is its start

    # no evaluation at all before the failure: FitError naming the stage and the outcome
    fake_first_stage(monkeypatch, [], ValueError("nlopt invalid argument"))
    with pytest.raises(FitError, match=r"stage 'first'.*INVALID_ARGS.*before any finite evaluation"):
        fit(ParamSet([Block("a", np.zeros(1))]), obj, [Stage("first", "a")], progress=False)


def test_forced_stop_from_the_objective_ends_the_stage_only():
    calls = []

    def obj(values, stage):
        calls.append(stage.name)
        if stage.name == "s1" and len(calls) == 3:
            raise nlopt.ForcedStop()
        d = values["a"] - 1.0
        return float(d @ d), {"a": 2 * d}, {}

    res = fit(ParamSet([Block("a", np.array([5.0, -3.0]))]), obj,
              [Stage("s1", "a"), Stage("s2", "a")], progress=False)
    assert res.outcomes["s1"] == "FORCED_STOP"
    assert calls.count("s1") == 3 and "s2" in calls
    np.testing.assert_allclose(res.values["a"], 1.0, atol=1e-6)


@pytest.mark.parametrize("how", ["raise", "sigint"])
def test_interruption_leaves_a_readable_checkpoint(tmp_path, how):
    if how == "sigint" and (threading.current_thread() is not threading.main_thread()
                            or signal.getsignal(signal.SIGINT) is not signal.default_int_handler):
        pytest.skip("needs the default SIGINT handler in the main thread")
    seen = []
    params = rosen_params(0.0, 0.0)

    def obj(values, stage):
        if len(seen) == 4:                       # evaluation 5
            if how == "raise":
                raise KeyboardInterrupt
            os.kill(os.getpid(), signal.SIGINT)  # a real Ctrl-C; this evaluation completes
        out = rosen(values, stage)
        seen.append((out[0], {k: v.copy() for k, v in values.items()}))
        return out

    res = fit(params, obj, [Stage("s1", ("x", "y"), max_iters=200),
                            Stage("s2", ("x",))], out_dir=tmp_path, progress=False)
    assert res.interrupted is True
    assert res.outcomes == {"s1": "INTERRUPTED"}       # s2 never started
    n = 4 if how == "raise" else 5
    assert len(seen) == n and len(res.history) == n
    best_loss, best_vals = min(seen, key=lambda s: s[0])
    assert best_loss < seen[0][0]
    ck = np.load(tmp_path / "checkpoint.npz")
    np.testing.assert_array_equal(ck["x"], best_vals["x"])
    np.testing.assert_array_equal(ck["y"], best_vals["y"])
    assert str(ck["__stage__"]) == "s1" and float(ck["__loss__"]) == best_loss
    values, meta = load_checkpoint(tmp_path / "checkpoint.npz")
    assert set(values) == {"x", "y"} and meta["stage"] == "s1" and meta["loss"] == best_loss
    assert meta["iter"] == 1 + [s[0] for s in seen].index(best_loss)
    np.testing.assert_array_equal(res.values["x"], best_vals["x"])
    np.testing.assert_array_equal(params.values()["y"], best_vals["y"])
    assert res.loss == best_loss
    assert json.loads((tmp_path / "history.json").read_text())["interrupted"] is True
    assert (tmp_path / "loss_curve.png").stat().st_size > 0
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


def test_sigterm_stops_like_ctrl_c_when_its_handler_raises_keyboard_interrupt(tmp_path):
    if threading.current_thread() is not threading.main_thread():
        pytest.skip("needs the main thread")
    previous = signal.signal(signal.SIGTERM, signal.default_int_handler)   # as `softras-cl` sets it
    try:
        seen = []

        def obj(values, stage):
            if len(seen) == 3:
                os.kill(os.getpid(), signal.SIGTERM)
            seen.append(1)
            return rosen(values, stage)

        res = fit(rosen_params(0.0, 0.0), obj, [Stage("s1", ("x", "y"), max_iters=200)],
                  out_dir=tmp_path, progress=False)
        assert res.interrupted and res.outcomes == {"s1": "INTERRUPTED"} and len(seen) == 4
        assert load_checkpoint(tmp_path / "checkpoint.npz")[1]["completed"] == 0
        assert signal.getsignal(signal.SIGTERM) is signal.default_int_handler
    finally:
        signal.signal(signal.SIGTERM, previous)


QUAD_STAGES = [Stage("coarse", ("a",), max_iters=60), Stage("fine", ("b",), max_iters=60)]


def test_resume_after_an_interrupt_in_the_second_stage_reaches_the_same_answer(tmp_path):
    uninterrupted = fit(quad_params(), Quadratic(), QUAD_STAGES, progress=False)
    calls = []

    def interrupted(values, stage):
        calls.append(stage.name)
        if stage.name == "fine" and calls.count("fine") == 3:
            raise KeyboardInterrupt
        return Quadratic()(values, stage)

    first = fit(quad_params(), interrupted, QUAD_STAGES, out_dir=tmp_path, progress=False)
    assert first.interrupted and load_checkpoint(tmp_path / "checkpoint.npz")[1]["completed"] == 1
    n_coarse = calls.count("coarse")

    obj = Quadratic()
    resumed = fit(quad_params(), obj, QUAD_STAGES, out_dir=tmp_path, progress=False, resume=True)
    assert not resumed.interrupted
    assert {s.name for s, *_ in obj.seen} == {"fine"}          # the finished stage is skipped
    np.testing.assert_array_equal(obj.seen[0][3]["a"], first.values["a"])   # from the checkpoint
    np.testing.assert_allclose(resumed.values["b"], uninterrupted.values["b"], rtol=1e-6)
    np.testing.assert_array_equal(resumed.values["a"], uninterrupted.values["a"])
    # the finished stage's history and outcome are read back; the interrupted stage reruns
    assert [h["stage"] for h in resumed.history] == ["coarse"] * n_coarse + ["fine"] * len(obj.seen)
    assert resumed.outcomes["coarse"] == first.outcomes["coarse"]
    assert load_checkpoint(tmp_path / "checkpoint.npz")[1]["completed"] == 2


def test_resume_of_a_finished_fit_runs_nothing(tmp_path):
    done = fit(quad_params(), Quadratic(), QUAD_STAGES, out_dir=tmp_path, progress=False)
    obj = Quadratic()
    again = fit(quad_params(), obj, QUAD_STAGES, out_dir=tmp_path, progress=False, resume=True)
    assert obj.seen == []
    for name in ("a", "b"):
        np.testing.assert_array_equal(again.values[name], done.values[name])


@pytest.mark.parametrize("damage", ["truncated", "bit flipped", "empty", "no metadata"])
def test_a_corrupt_checkpoint_is_an_input_error_naming_the_file(tmp_path, damage):
    """Resuming from a damaged checkpoint.npz says which file is corrupt and what to do."""
    fit(quad_params(), Quadratic(), QUAD_STAGES, out_dir=tmp_path, progress=False)
    path = tmp_path / "checkpoint.npz"
    data = path.read_bytes()
    if damage == "truncated":
        path.write_bytes(data[:len(data) // 2])
    elif damage == "bit flipped":                 # inside the first array's data: a CRC error
        path.write_bytes(data[:120] + bytes([data[120] ^ 0xFF]) + data[121:])
    elif damage == "empty":
        path.write_bytes(b"")
    else:
        np.savez(path, **load_checkpoint(path)[0])
    with pytest.raises(InputError) as caught:
        fit(quad_params(), Quadratic(), QUAD_STAGES, out_dir=tmp_path, progress=False, resume=True)
    message = str(caught.value)
    assert f"checkpoint {path} is corrupt" in message
    assert "start the fit again without --resume" in message


def test_resume_refuses_a_missing_or_foreign_checkpoint(tmp_path):
    with pytest.raises(ValueError, match="does not exist"):
        fit(quad_params(), Quadratic(), QUAD_STAGES, out_dir=tmp_path, progress=False, resume=True)
    fit(rosen_params(), rosen, [Stage("s1", ("x", "y"), max_iters=3)], out_dir=tmp_path, progress=False)
    with pytest.raises(ValueError, match="checkpoint of another fit"):
        fit(quad_params(), Quadratic(), QUAD_STAGES, out_dir=tmp_path, progress=False, resume=True)
    (tmp_path / "checkpoint.npz").write_bytes(b"not an npz")
    with pytest.raises(InputError, match="is corrupt .not an .npz archive"):
        fit(quad_params(), Quadratic(), QUAD_STAGES, out_dir=tmp_path, progress=False, resume=True)
    with pytest.raises(ValueError, match="needs out_dir"):
        fit(quad_params(), Quadratic(), QUAD_STAGES, progress=False, resume=True)


def test_nan_gradient_raises_naming_stage_and_block(tmp_path):
    params = quad_params()
    n = [0]

    def obj(values, stage):
        loss, grads, terms = Quadratic()(values, stage)
        if stage.name == "refine":
            n[0] += 1
            if n[0] == 3:
                grads["b"] = grads["b"].copy()
                grads["b"][1, 0] = np.nan
        return loss, grads, terms

    stages = [Stage("warmup", ("a",), max_iters=5), Stage("refine", ("a", "b"), max_iters=50)]
    with pytest.raises(FitError) as err:
        fit(params, obj, stages, out_dir=tmp_path, progress=False)
    msg = str(err.value)
    assert "'refine'" in msg and "evaluation 3" in msg
    assert "gradient not finite in block(s) 'b'" in msg and "'a'" not in msg
    assert err.value.stage == "refine" and err.value.blocks == ("b",) and err.value.iter == 3
    # the best point so far was written before raising
    values, meta = load_checkpoint(tmp_path / "checkpoint.npz")
    assert meta["stage"] == "refine"


def test_nan_loss_and_inf_gradient_in_a_frozen_block():
    def obj(values, stage):
        terms = {"data": float("nan"), "prior": 1.0}
        return float("nan"), {"a": np.ones(3), "b": np.full((2, 2), np.inf)}, terms

    with pytest.raises(FitError, match=r"stage 's'.*loss is nan.*all free blocks are finite"
                                       r".*non-finite term\(s\): data"):
        fit(quad_params(), obj, [Stage("s", ("a",))], progress=False)

    def obj2(values, stage):
        return 1.0, {"a": np.array([0.0, np.inf, 0.0]), "b": np.full((2, 2), np.nan)}, {}
    with pytest.raises(FitError, match=r"stage 't'.*block\(s\) 'a', 'b'"):
        fit(quad_params(), obj2, [Stage("t", ("a", "b"))], progress=False)


def test_objective_bug_is_reraised_unchanged():
    def obj(values, stage):
        raise ZeroDivisionError("bug in the objective")
    with pytest.raises(ZeroDivisionError, match="bug in the objective"):
        fit(quad_params(), obj, [Stage("s", ("a",))], progress=False)


def test_files_written(tmp_path, monkeypatch):
    monkeypatch.setattr(solver_module, "CHECKPOINT_INTERVAL", 0.0)
    ck = tmp_path / "out" / "checkpoint.npz"
    during = []

    def obj(values, stage):
        loss, grads, terms = Quadratic()(values, stage)
        if ck.exists():
            during.append(float(np.load(ck)["__loss__"]))
        return loss, grads, terms

    stages = [Stage("one", ("a",), max_iters=20), Stage("two", ("b",), max_iters=20)]
    res = fit(quad_params(), obj, stages, out_dir=tmp_path / "out", progress=False)
    assert during and during == sorted(during, reverse=True)   # written as it goes, best so far
    files = sorted(os.listdir(tmp_path / "out"))
    assert files == ["checkpoint.npz", "history.json", "loss_curve.png"]   # no temp files left
    png = (tmp_path / "out" / "loss_curve.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    doc = json.loads((tmp_path / "out" / "history.json").read_text())
    assert doc["outcomes"] == res.outcomes and doc["interrupted"] is False
    assert [s["name"] for s in doc["stages"]] == ["one", "two"]
    assert len(doc["history"]) == len(res.history)
    assert doc["history"][0] == {"stage": "one", "iter": 1, "loss": res.history[0]["loss"],
                                 "terms": res.history[0]["terms"]}
    values, meta = load_checkpoint(tmp_path / "out" / "checkpoint.npz")
    assert meta["stage"] == "two" and meta["loss"] == res.loss
    np.testing.assert_array_equal(values["b"], res.values["b"])


def test_progress_bar(capsys):
    fit(quad_params(), Quadratic(), [Stage("stage-xyz", ("a",), max_iters=10)], progress=True)
    err = capsys.readouterr().err
    assert "stage-xyz" in err and "loss=" in err and "iter=" in err
    fit(quad_params(), Quadratic(), [Stage("stage-xyz", ("a",), max_iters=10)], progress=False)
    assert capsys.readouterr().err == ""


@pytest.mark.parametrize("stages,pattern", [
    ([Stage("s", ("nope",))], r"stage 's'.*unknown block 'nope'"),
    ([Stage("s", ())], r"stage 's': no free blocks"),
    ([Stage("s", ("a",)), Stage("s", ("b",))], r"duplicate stage name 's'"),
    ([Stage("s", ("a",), max_iters=0)], r"stage 's': max_iters"),
    ([], r"at least one stage"),
])
def test_bad_stages(stages, pattern):
    with pytest.raises(ValueError, match=pattern):
        fit(quad_params(), Quadratic(), stages, progress=False)


CURVATURES = np.logspace(0, 4, 40)


def offset_quadratic(values, stage):
    """1 + sum_i c_i (a_i - 1)^2, curvatures 1..1e4: L-BFGS needs over a hundred evaluations,
    and near the minimum the relative improvement of its tail falls below any stall_rel."""
    d = values["a"] - 1.0
    return 1.0 + float(np.sum(CURVATURES * d * d)), {"a": 2 * CURVATURES * d}, {}


def slow_params():
    return ParamSet([Block("a", np.zeros(CURVATURES.size))])


SLOW = Stage("slow", "a", max_iters=1000, ftol_rel=0, xtol_rel=0)


def test_stall_window_stops_a_stage_before_its_cap_and_says_why():
    """Without the window (and without tolerances) nlopt runs this stage until its own test;
    the window stops it earlier, once 10 evaluations improved the best by <= 1e-5 relative."""
    plain = fit(slow_params(), offset_quadratic, [SLOW], progress=False)
    res = fit(slow_params(), offset_quadratic,
              [dataclasses.replace(SLOW, stall_window=10, stall_rel=1e-5), Stage("next", "a", max_iters=2)],
              progress=False)
    assert plain.outcomes["slow"] != "STALLED"
    assert res.outcomes["slow"] == "STALLED" and "next" in res.outcomes
    n = sum(h["stage"] == "slow" for h in res.history)
    assert 10 < n < len(plain.history) < SLOW.max_iters
    best = np.minimum.accumulate([h["loss"] for h in res.history[:n]])
    assert best[-11] - best[-1] <= 1e-5 * best[-1]                  # the rule held at the stop
    assert all(best[k - 10] - best[k] > 1e-5 * best[k] for k in range(10, n - 1))   # not before
    assert res.loss == pytest.approx(1.0, abs=1e-4)


def test_stall_window_on_scripted_losses_stops_at_the_first_flat_window(monkeypatch):
    """best after each evaluation 10, 9, 8, 8, 8, 8, ...: with a window of 3 and stall_rel 0
    the stage ends at evaluation 6 (best(3) - best(6) = 0), not at the first flat step."""
    losses = iter([10.0, 9.0, 8.0, 8.5, 8.0, 9.0, 7.0, 7.0])
    fake_first_stage(monkeypatch, [[0.0]] * 8, nlopt.ForcedStop("as nlopt ends a forced stop"))
    calls = []

    def obj(values, stage):
        calls.append(stage.name)
        return next(losses), {"a": np.zeros(1)}, {}

    res = fit(ParamSet([Block("a", np.zeros(1))]), obj,
              [Stage("s1", "a", stall_window=3), Stage("s2", "a", max_iters=1)], progress=False)
    assert calls.count("s1") == 6 and res.outcomes["s1"] == "STALLED"


def test_a_stalled_stage_is_finished_for_resume(tmp_path):
    stages = [dataclasses.replace(SLOW, stall_window=10, stall_rel=1e-5), Stage("next", "a", max_iters=50)]
    calls = []

    def interrupted(values, stage):
        calls.append(stage.name)
        if stage.name == "next" and calls.count("next") == 2:
            raise KeyboardInterrupt
        return offset_quadratic(values, stage)

    first = fit(slow_params(), interrupted, stages, out_dir=tmp_path, progress=False)
    assert first.interrupted and first.outcomes["slow"] == "STALLED"
    seen = []
    resumed = fit(slow_params(), lambda v, s: seen.append(s.name) or offset_quadratic(v, s), stages,
                  out_dir=tmp_path, progress=False, resume=True)
    assert set(seen) == {"next"}                       # the stalled stage is not run again
    assert resumed.outcomes["slow"] == "STALLED"
    assert [h["stage"] for h in resumed.history].count("slow") == calls.count("slow")
    assert resumed.loss <= first.loss


@pytest.mark.parametrize("changes,pattern", [
    (dict(stall_window=-1), r"stage 's': stall_window must be an integer >= 0"),
    (dict(stall_window=2.5), r"stall_window must be an integer"),
    (dict(stall_rel=-1e-3), r"stall_rel must be >= 0"),
])
def test_bad_stall_settings(changes, pattern):
    with pytest.raises(ValueError, match=pattern):
        fit(quad_params(), Quadratic(), [Stage("s", ("a",), **changes)], progress=False)
