"""fitting/params.py (docs/fitting.md): named blocks <-> flat scaled vector, bounds, gradients,
and bad input raising ValueError that names the block."""
import numpy as np
import pytest

from softras_cl.fitting.params import Block, ParamSet

RNG = np.random.default_rng(3)


def make():
    return ParamSet([
        Block("rot", np.array([0.1, -0.2, 0.3]), lower=-np.pi, upper=np.pi, scale=0.5),
        Block("t", np.array(2.5), lower=0.0, scale=10.0),                       # 0-d block
        Block("shape", RNG.normal(size=(2, 3)), scale=np.array([1.0, 2.0, 4.0])),  # broadcast scale
        Block("sh", np.zeros(4), upper=np.array([1.0, 2.0, 3.0, 4.0])),
    ])


def test_names_sizes_and_layout_follow_block_order():
    p = make()
    assert p.names == ("rot", "t", "shape", "sh")
    assert p.size() == 3 + 1 + 6 + 4
    assert p.size(["sh", "rot"]) == 7
    # the layout is the ParamSet order whatever the order of `free`
    assert list(p.slices(["sh", "rot"])) == ["rot", "sh"]
    assert p.slices(["sh", "rot"])["sh"] == slice(3, 7)
    vals = p.values()
    np.testing.assert_array_equal(p.pack(vals, ["sh", "rot"]), p.pack(vals, ["rot", "sh"]))
    np.testing.assert_array_equal(p.pack(vals, "t"), [0.25])          # a single name is accepted


def test_pack_divides_by_scale_and_unpack_round_trips():
    p = make()
    vals = p.values()
    free = ["rot", "t", "shape", "sh"]
    x = p.pack(vals, free)
    assert x.dtype == np.float64 and x.shape == (14,)
    np.testing.assert_allclose(x[:3], vals["rot"] / 0.5)
    np.testing.assert_allclose(x[3], 2.5 / 10.0)
    np.testing.assert_allclose(x[4:10], (vals["shape"] / [1.0, 2.0, 4.0]).ravel())
    back = p.unpack(x, free, vals)
    for n in p.names:
        assert back[n].shape == vals[n].shape
        np.testing.assert_allclose(back[n], vals[n], rtol=1e-15, atol=0)
    # unpack(pack) of a new point, then pack again
    x2 = x + RNG.normal(size=x.shape) * 0.01
    np.testing.assert_allclose(p.pack(p.unpack(x2, free, vals), free), x2, rtol=1e-15)


def test_unpack_replaces_only_free_blocks():
    p = make()
    base = p.values()
    base["sh"] = np.array([0.5, 0.5, 0.5, 0.5])
    x = np.array([1.0, 2.0, 3.0, 0.2])                       # rot (scaled) then t (scaled)
    out = p.unpack(x, ["t", "rot"], base)
    np.testing.assert_allclose(out["rot"], [0.5, 1.0, 1.5])
    np.testing.assert_allclose(out["t"], 2.0)
    assert out["sh"] is base["sh"] and out["shape"] is base["shape"]
    # default base: the current values
    out2 = p.unpack(x, ["t", "rot"])
    np.testing.assert_array_equal(out2["sh"], np.zeros(4))
    with pytest.raises(ValueError, match=r"x has shape"):
        p.unpack(np.zeros(5), ["t", "rot"], base)


def test_unpack_clips_to_bounds():
    p = ParamSet([Block("a", np.array([0.3, 0.3]), lower=0.1, upper=0.7, scale=0.3)])
    lo, hi = p.bounds(["a"])
    out = p.unpack(np.array([lo[0], hi[1]]) * (1 + 1e-15), ["a"], p.values())
    assert np.all(out["a"] >= 0.1) and np.all(out["a"] <= 0.7)


def test_bounds_in_scaled_units():
    p = make()
    lo, hi = p.bounds(["rot", "t", "shape", "sh"])
    np.testing.assert_allclose(lo[:3], -np.pi / 0.5)
    np.testing.assert_allclose(hi[:3], np.pi / 0.5)
    assert lo[3] == 0.0 and hi[3] == np.inf
    assert np.all(lo[4:10] == -np.inf) and np.all(hi[4:10] == np.inf)
    assert np.all(lo[10:] == -np.inf)
    np.testing.assert_allclose(hi[10:], [1.0, 2.0, 3.0, 4.0])
    # the starting point is inside the scaled bounds
    x = p.pack(p.values(), p.names)
    assert np.all(x >= lo) and np.all(x <= hi)
    # subset
    lo2, hi2 = p.bounds(["sh"])
    np.testing.assert_allclose(hi2, [1.0, 2.0, 3.0, 4.0])


def test_pack_grad_is_the_gradient_wrt_x():
    """pack_grad(d L/d values) == d/dx L(unpack(x)) by central differences."""
    p = make()
    coef = {n: RNG.normal(size=p.shape(n)) for n in p.names}

    def loss(vals):
        return sum(float(np.sum(coef[n] * vals[n] ** 2 + np.sin(vals[n]))) for n in vals)

    def grads(vals):
        return {n: 2 * coef[n] * vals[n] + np.cos(vals[n]) for n in vals}

    base = p.values()
    free = ["shape", "t", "rot"]
    x = p.pack(base, free)
    g = p.pack_grad(grads(p.unpack(x, free, base)), free)
    h = 1e-6
    fd = np.array([(loss(p.unpack(x + h * e, free, base)) - loss(p.unpack(x - h * e, free, base)))
                   / (2 * h) for e in np.eye(x.size)])
    np.testing.assert_allclose(g, fd, rtol=1e-6, atol=1e-8)


def test_pack_grad_missing_block_is_zero_and_frozen_ignored():
    p = make()
    g = p.pack_grad({"t": np.array(3.0), "sh": np.ones(4)}, ["rot", "t"])   # rot missing, sh frozen
    np.testing.assert_array_equal(g, [0.0, 0.0, 0.0, 30.0])
    with pytest.raises(ValueError, match=r"'rot'.*shape"):
        p.pack_grad({"rot": np.ones(4)}, ["rot"])


def test_values_are_copies_and_set_validates():
    p = make()
    v = p.values()
    v["rot"][0] = 99.0
    assert p.values()["rot"][0] == 0.1
    p.set({"rot": np.array([1.0, 1.0, 1.0])})
    np.testing.assert_array_equal(p.values()["rot"], 1.0)
    with pytest.raises(ValueError, match=r"'rot'.*outside its bounds"):
        p.set({"rot": np.array([4.0, 0.0, 0.0])})
    with pytest.raises(ValueError, match=r"'sh'.*not finite"):
        p.set({"sh": np.array([np.nan, 0, 0, 0])})
    with pytest.raises(ValueError, match=r"'t'.*shape"):
        p.set({"t": np.array([1.0])})
    with pytest.raises(ValueError, match=r"unknown block 'nope'"):
        p.set({"nope": 1.0})
    np.testing.assert_array_equal(p.values()["rot"], 1.0)      # failed sets changed nothing


@pytest.mark.parametrize("blocks,pattern", [
    ([Block("a", np.zeros(2)), Block("a", np.ones(3))], r"duplicate block name 'a'"),
    ([Block("a", np.zeros(2)), Block("b", np.array([0.0, np.nan]))], r"block 'b'.*init is not finite"),
    ([Block("c", np.array([1.0, np.inf]))], r"block 'c'.*init is not finite"),
    ([Block("d", np.zeros(2), lower=1.0, upper=0.5)], r"block 'd'.*lower > upper"),
    ([Block("e", np.zeros(2), lower=np.array([0.0, -1.0]), upper=np.array([-0.5, 1.0]))],
     r"block 'e'.*lower > upper"),
    ([Block("f", np.array([2.0]), upper=1.0)], r"block 'f'.*init outside its bounds"),
    ([Block("g", np.array([-2.0, 0.0]), lower=-1.0)], r"block 'g'.*init outside its bounds"),
    ([Block("h", np.zeros(2), scale=0.0)], r"block 'h'.*scale"),
    ([Block("i", np.zeros(2), scale=-1.0)], r"block 'i'.*scale"),
    ([Block("j", np.zeros(3), scale=np.array([1.0, 0.0, 1.0]))], r"block 'j'.*scale"),
    ([Block("k", np.zeros(3), scale=np.ones(2))], r"block 'k'.*scale.*broadcast"),
    ([Block("l", np.zeros(3), lower=np.zeros(4))], r"block 'l'.*lower.*broadcast"),
])
def test_bad_blocks_raise_naming_the_block(blocks, pattern):
    with pytest.raises(ValueError, match=pattern):
        ParamSet(blocks)


def test_unknown_names_in_free_values_and_grads():
    p = make()
    v = p.values()
    with pytest.raises(ValueError, match=r"unknown block 'rotation'"):
        p.pack(v, ["rotation"])
    with pytest.raises(ValueError, match=r"unknown block 'zz'"):
        p.bounds(["rot", "zz"])
    with pytest.raises(ValueError, match=r"unknown block 'zz'"):
        p.unpack(np.zeros(3), ["zz"], v)
    with pytest.raises(ValueError, match=r"unknown block.*'extra'.*values"):
        p.pack({**v, "extra": np.zeros(1)}, ["rot"])
    with pytest.raises(ValueError, match=r"unknown block.*'extra'.*grads"):
        p.pack_grad({"extra": np.zeros(1)}, ["rot"])
    with pytest.raises(ValueError, match=r"'rot'.*more than once"):
        p.pack(v, ["rot", "rot"])
    with pytest.raises(ValueError, match=r"'sh' is free but missing"):
        p.pack({"rot": v["rot"]}, ["rot", "sh"])
