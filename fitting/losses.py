"""Loss terms for fitting, each a pure float64 numpy function with an exact gradient.

Every loss returns ``(value, grads)``: ``value`` a Python float and ``grads`` a dict mapping the
name of each differentiable argument (``"pred"``, ``"points"``, ``"coeffs"``, ``"vertices"``) to a
float64 array of that argument's shape. Targets, masks, weights and sigmas are constants (no
gradient). Weights between terms are applied in one place, :func:`weighted_sum`.

Invalid inputs raise ``ValueError`` whose message starts with the argument's name: wrong shapes,
NaN or infinite values, negative weights or masks, non-positive sigmas, bad face indices (the
checks of :mod:`softras_cl.checks`, shared with every other entry point).

Losses are the one deliberate exception to the project's ``y, ctx = f(x)`` /
``f_vjp(ctx, grad_y)`` convention. A loss is a scalar terminal: its cotangent is always 1
(a weight, applied by :func:`weighted_sum`), so its gradient costs no more than its value and
there is nothing to keep between the two; a context and a second call would only add a step
to every fit.

Mesh terms (:func:`laplacian`, :func:`flatten`, :func:`edge_length`) share a topology (unique
edges, vertex degrees, interior edges with their two opposite vertices) computed once per face
array by :func:`mesh_topology` and cached, so calling them every iteration of a fit costs only
the vectorised arithmetic (``np.bincount`` scatters, no Python loop over vertices or edges).
"""
from __future__ import annotations

import hashlib
from collections import OrderedDict
from dataclasses import dataclass
from typing import Mapping

import numpy as np

from softras_cl.checks import index_array, nonnegative, positive, real_array

IOU_EPS = 1e-6      # silhouette_iou's guard, in summed pixel values

__all__ = [
    "MeshTopology", "mesh_topology",
    "image_l2", "image_l1", "image_geman_mcclure", "GemanMcClure", "silhouette_iou", "silhouette_l2", "landmarks_2d",
    "landmarks_2d_unchecked", "landmarks_2d_robust", "gaussian_prior", "gaussian_prior_unchecked", "sh_white", "laplacian_coordinates", "laplacian", "flatten", "edge_length",
    "weighted_sum",
]


# ---------------------------------------------------------------------------------------------
# validation helpers
# ---------------------------------------------------------------------------------------------

def _same_shape(a: np.ndarray, b: np.ndarray, name_a: str, name_b: str) -> None:
    if a.shape != b.shape:
        raise ValueError(f"{name_b}: shape {b.shape} does not match {name_a} shape {a.shape}")


def _image_pair(pred, target) -> tuple[np.ndarray, np.ndarray]:
    p = real_array("pred", pred)
    t = real_array("target", target)
    _same_shape(p, t, "pred", "target")
    return p, t


def _image_mask(mask, shape: tuple) -> np.ndarray | None:
    """Mask as float64 broadcast to ``shape`` (H, W) or (H, W, C); None for no mask."""
    if mask is None:
        return None
    m = real_array("mask", mask)
    nonnegative("mask", m)
    if len(shape) == 3 and m.shape == shape[:2]:
        m = m[:, :, None]                    # an (H, W) mask applies to every channel
    try:
        return np.broadcast_to(m, shape)
    except ValueError:
        raise ValueError(f"mask: shape {np.shape(mask)} is neither pred's (H, W) = {shape[:2]} "
                         f"nor broadcastable to pred's shape {shape}") from None


# ---------------------------------------------------------------------------------------------
# image terms
# ---------------------------------------------------------------------------------------------

def _masked_mean(elementwise: np.ndarray, d_elementwise: np.ndarray, m: np.ndarray | None,
                 ) -> tuple[float, dict]:
    if m is None:
        n = elementwise.size
        if n == 0:
            return 0.0, {"pred": np.zeros_like(elementwise)}
        return float(elementwise.sum() / n), {"pred": d_elementwise / n}
    total = float(m.sum())
    if total == 0.0:
        return 0.0, {"pred": np.zeros_like(elementwise)}
    return float((m * elementwise).sum() / total), {"pred": m * d_elementwise / total}


def image_l2(pred, target, mask=None) -> tuple[float, dict]:
    """Mean squared error between two images.

    ``pred`` and ``target``: arrays of the same shape, (H, W) or (H, W, C) (any shape is
    accepted; the mean then runs over all elements). ``mask``: None, an (H, W) array applied to
    every channel of an (H, W, C) image, or any array broadcastable to ``pred``'s shape; its
    values are non-negative per-pixel weights (boolean or 0/1 for a plain mask).

    With ``m`` the mask broadcast to ``pred``'s shape (all ones when None)::

        value = sum(m * (pred - target)**2) / sum(m)

    i.e. the mean over masked pixels *and* channels (a pixel of an (H, W, C) image counts C
    times). An all-zero mask (or an empty image) gives 0 and a zero gradient.
    Returns ``(value, {"pred": 2 * m * (pred - target) / sum(m)})``.
    """
    p, t = _image_pair(pred, target)
    m = _image_mask(mask, p.shape)
    r = p - t
    return _masked_mean(r * r, 2.0 * r, m)


def image_l1(pred, target, mask=None) -> tuple[float, dict]:
    """Mean absolute error between two images: ``sum(m * |pred - target|) / sum(m)``.

    Shapes, the mask and the normalisation exactly as in :func:`image_l2`. The gradient wrt
    ``pred`` is ``m * sign(pred - target) / sum(m)``, taking the subgradient 0 where
    ``pred == target``.
    """
    p, t = _image_pair(pred, target)
    m = _image_mask(mask, p.shape)
    r = p - t
    return _masked_mean(np.abs(r), np.sign(r), m)


def image_geman_mcclure(pred, target, scale, mask=None) -> tuple[float, dict]:
    """Robust image error: the Geman-McClure kernel of each pixel's squared colour error.

    ``pred``, ``target``: (H, W, C) images (the squared error of a pixel sums its C channels)
    or (H, W) (one channel); ``scale``: s > 0, in the images' units; ``mask``: None or (H, W)
    non-negative per-pixel weights. With ``r2_p = sum_c (pred - target)[p, c]**2``::

        rho(r2) = r2 / (1 + r2 / s**2)        ~ r2 for r << s, -> s**2 for r >> s
        value   = sum_p m_p rho(r2_p) / sum_p m_p

    so small errors count as in :func:`image_l2` (times C) and a pixel the model cannot
    explain (a cast shadow, a highlight, a hair strand) adds at most s**2 and pulls less the
    further it is off (its gradient ``2 (pred - target) / (1 + r2 / s**2)**2`` falls as 1/r**3).
    Finite for any finite inputs whose true value is representable: the kernel is evaluated
    on ``(pred - target) / s``, so neither a tiny nor a huge scale overflows or divides 0 by 0.
    An all-zero mask gives 0. Returns ``(value, {"pred": gradient of pred's shape})``.
    """
    p, _ = _image_pair(pred, target)
    if p.ndim not in (2, 3):
        raise ValueError(f"pred: expected an (H, W) or (H, W, C) image, got shape {p.shape}")
    return GemanMcClure(target, scale, mask)(p)


class GemanMcClure:
    """:func:`image_geman_mcclure` with its target, scale and mask fixed, for a loss evaluated
    many times (a fit's stage): their checks, the pixels of positive weight and those pixels'
    target colours are taken once, here. ``loss(pred) -> (value, {"pred": gradient})``, the
    same values to the bit as image_geman_mcclure(pred, target, scale, mask);
    ``loss(pred, grad_scale)`` returns the gradient times grad_scale (the same bits as
    multiplying it afterwards, without another pass over the whole image).
    """

    def __init__(self, target, scale, mask=None):
        t = real_array("target", target)
        if t.ndim not in (2, 3):
            raise ValueError(f"target: expected an (H, W) or (H, W, C) image, got shape {t.shape}")
        s = real_array("scale", scale)
        if s.ndim != 0:
            raise ValueError(f"scale: expected a scalar, got shape {s.shape}")
        positive("scale", s)
        self.shape, self.scale = t.shape, float(s)
        m = _image_mask(mask, t.shape[:2])
        weights = (np.ones(t.shape[:2]) if m is None else m).reshape(-1)
        self.total = float(weights.sum())
        # only pixels of positive weight add to the sum (the others add exact zeros): the
        # kernel is evaluated on those alone (a face region is a fraction of the image), held
        # channel-major (C, N) so that every step runs over contiguous rows
        self.keep = np.flatnonzero(weights)
        self.weights = weights[self.keep]
        channels = t.shape[2] if t.ndim == 3 else 1
        self.elements = (self.keep * channels + np.arange(channels)[:, None]).reshape(-1)
        self.target = t.reshape(-1).take(self.elements).reshape(channels, -1)

    def __call__(self, pred, grad_scale: float = 1.0) -> tuple[float, dict]:
        p = real_array("pred", pred)
        if p.shape != self.shape:
            raise ValueError(f"pred: shape {p.shape} does not match target shape {self.shape}")
        grad = np.zeros(p.size)
        if self.total == 0.0:
            return 0.0, {"pred": grad.reshape(p.shape)}
        s = self.scale
        r = p.reshape(-1).take(self.elements).reshape(self.target.shape) - self.target
        with np.errstate(over="ignore", under="ignore", invalid="ignore"):
            z2 = _channel_sum(np.square(r / s))                 # inf where r >> s: then w = 0
            w = 1.0 / (1.0 + z2)
            # z2 <= 1: r2 is at most C s**2; z2 > 1: 1 - w has no cancellation and rho <= s**2
            rho = np.where(z2 <= 1.0, _channel_sum(np.square(r)) * w, (s * s) * (1.0 - w))
            weighted = np.zeros(self.shape[:2])
            np.put(weighted, self.keep, self.weights * rho)
            np.put(grad, self.elements, (self.weights / self.total) * ((2.0 * w * w) * r) * grad_scale)
        return float(weighted.sum() / self.total), {"pred": grad.reshape(p.shape)}


def _channel_sum(rows: np.ndarray) -> np.ndarray:
    """(C, N) -> (N,): the channels added first to last, the order of numpy's sum over a
    pixel's few channels (so the same bits as (N, C).sum(axis=-1), C < 8), without its cost."""
    total = rows[0].copy()
    for row in rows[1:]:
        total += row
    return total


def silhouette_iou(pred, target, eps: float = IOU_EPS, mask=None) -> tuple[float, dict]:
    """Soft IoU loss of the paper (sec. 4.1): ``1 - sum(p t) / sum(p + t - p t)``.

    ``pred``, ``target``: silhouettes (alpha in [0, 1]) of the same shape, e.g. (H, W); the sums
    run over all elements (stacked views are pooled into one IoU). With ``I = sum(p t)`` and
    ``U = sum(p + t - p t)`` the value computed is::

        value = (U - I) / (U + eps)  =  1 - (I + eps) / (U + eps)

    which is the paper's loss up to ``eps`` (in units of summed pixel values, so negligible for
    any non-trivial silhouette): identical binary masks give exactly 0, disjoint ones
    ``U / (U + eps)`` ~ 1, and an empty union (both all zero) gives 0 with a finite gradient
    (of size ~1/eps: the unguarded loss is discontinuous there). ``eps`` must be > 0.
    Returns ``(value, {"pred": d value / d pred})``; the gradient is exact for the guarded
    formula: ``((1 - 2t)(U + eps) - (U - I)(1 - t)) / (U + eps)**2``.

    ``mask``: None, or non-negative per-pixel weights w (checked and broadcast as in
    :func:`image_l2`) that both sums take (``I = sum(w p t)``, ``U = sum(w (p + t - p t))``): 0
    leaves a pixel out, e.g. where the target is known to be wrong; the gradient is then the
    formula above times w.
    """
    p, t = _image_pair(pred, target)
    eps = float(real_array("eps", eps))
    positive("eps", np.asarray(eps))
    w = 1.0 if mask is None else _image_mask(mask, p.shape)
    inter = float((w * p * t).sum())
    union = float((w * (p + t - p * t)).sum())
    den = union + eps
    value = (union - inter) / den
    grad = w * ((1.0 - 2.0 * t) * den - (union - inter) * (1.0 - t)) / (den * den)
    return float(value), {"pred": grad}


def silhouette_l2(pred, target, mask=None) -> tuple[float, dict]:
    """Mean squared error between two silhouettes; identical to :func:`image_l2`.

    ``value = sum(m * (pred - target)**2) / sum(m)`` (``m`` all ones without a mask), so 0 for
    equal silhouettes and 1 for complementary binary ones. Returns ``(value, {"pred": ...})``.
    """
    return image_l2(pred, target, mask)


# ---------------------------------------------------------------------------------------------
# landmarks and priors
# ---------------------------------------------------------------------------------------------

def landmarks_2d(points, target, weights=None, robust_sigma=None) -> tuple[float, dict]:
    """2D landmark reprojection error, optionally with a Geman-McClure robust kernel.

    ``points``: projected landmarks (N, 2) in pixels (differentiable); ``target``: (N, 2)
    observed positions; ``weights``: None (all 1), a scalar, or (N,) non-negative per-point
    weights; ``robust_sigma``: None or a scale s > 0 in pixels. With ``r2_i = |points_i -
    target_i|^2``::

        rho(r2) = r2                     (robust_sigma None: squared distance, pixels^2)
        rho(r2) = r2 / (r2 + s**2)       (Geman-McClure: ~r2/s^2 for small residuals,
                                          saturating at 1 for r >> s; dimensionless)
        value   = (1/N) * sum_i weights_i * rho(r2_i)

    (the mean over points, not normalised by the weights' sum). N = 0 gives 0.
    Returns ``(value, {"points": (N, 2) gradient})``.
    """
    p = real_array("points", points)
    if p.ndim != 2 or p.shape[1] != 2:
        raise ValueError(f"points: expected shape (N, 2), got {p.shape}")
    t = real_array("target", target)
    _same_shape(p, t, "points", "target")
    n = p.shape[0]
    if weights is None:
        w = np.ones(n)
    else:
        w = real_array("weights", weights)
        if w.ndim == 0:
            w = np.full(n, float(w))
        elif w.shape != (n,):
            raise ValueError(f"weights: expected a scalar or shape ({n},), got {w.shape}")
        nonnegative("weights", w)
    if robust_sigma is not None:
        s = real_array("robust_sigma", robust_sigma)
        if s.ndim != 0:
            raise ValueError(f"robust_sigma: expected a scalar, got shape {s.shape}")
        positive("robust_sigma", s)
        robust_sigma = float(s)
    value, grad = landmarks_2d_unchecked(p - t, w, robust_sigma)
    return value, {"points": grad}


def landmarks_2d_unchecked(residuals: np.ndarray, weights: np.ndarray,
                           robust_sigma: float | None = None) -> tuple[float, np.ndarray]:
    """:func:`landmarks_2d`'s value and gradient wrt the points, from the residuals (N, D)
    float64 (points - target), weights (N,) float64 >= 0 and robust_sigma (a float > 0 or
    None), none of them checked: for a fit's own arrays, every evaluation."""
    n = len(residuals)
    if n == 0:
        return 0.0, np.zeros_like(residuals)
    r2 = np.einsum("ij,ij->i", residuals, residuals)
    if robust_sigma is None:
        rho, drho = r2, np.ones(n)
    else:
        s2 = robust_sigma ** 2
        den = r2 + s2
        rho, drho = r2 / den, s2 / (den * den)
    return float((weights * rho).sum() / n), (2.0 / n) * (weights * drho)[:, None] * residuals


def landmarks_2d_robust(residuals: np.ndarray, weights: np.ndarray, scale: float) -> tuple[float, np.ndarray]:
    """Landmark term robust to a detector's gross misses: each point's squared residual in its
    own standard deviations, ``u2_i = weights_i * |residuals_i|^2`` (weights_i = 1 / sigma_i^2),
    through Geman-McClure at ``scale`` c of them::

        rho(u2) = c^2 u2 / (u2 + c^2)     (~u2, the plain term, well below c; at most c^2)
        value   = (1/N) * sum_i rho(u2_i)

    residuals (N, D) float64 (points - target), weights (N,) >= 0, scale c > 0; none checked
    (a fit's own arrays, every evaluation). Returns (value, its gradient wrt the points (N, D))."""
    n = len(residuals)
    if n == 0:
        return 0.0, np.zeros_like(residuals)
    c2 = scale * scale
    u2 = weights * np.einsum("ij,ij->i", residuals, residuals)
    den = u2 + c2
    return float((c2 * u2 / den).sum() / n), (2.0 / n) * (weights * (c2 * c2) / (den * den))[:, None] * residuals


def gaussian_prior(coeffs, sigma, mean=0.0) -> tuple[float, dict]:
    """Gaussian prior (negative log-likelihood up to a factor 1/2): ``sum(((c - mean) / sigma)**2)``.

    ``coeffs``: any shape (differentiable). ``sigma``: a scalar or an array broadcastable to
    ``coeffs``' shape (per-coefficient standard deviations), all > 0. ``mean``: scalar or
    broadcastable, default 0. Returns ``(value, {"coeffs": 2 (c - mean) / sigma**2})``.
    """
    c = real_array("coeffs", coeffs)
    s = real_array("sigma", sigma)
    positive("sigma", s)
    mu = real_array("mean", mean)
    for a, name in ((s, "sigma"), (mu, "mean")):
        try:
            if np.broadcast_shapes(a.shape, c.shape) != c.shape:
                raise ValueError
        except ValueError:
            raise ValueError(f"{name}: shape {a.shape} does not broadcast to coeffs shape "
                             f"{c.shape}") from None
    value, grad = gaussian_prior_unchecked(c, s, mu)
    return value, {"coeffs": np.broadcast_to(grad, c.shape).copy()}


def gaussian_prior_unchecked(coeffs: np.ndarray, sigma, mean=0.0) -> tuple[float, np.ndarray]:
    """:func:`gaussian_prior`'s value and gradient (broadcast shape of the three) of float64
    arrays (or floats) not checked: for a fit's own blocks, every evaluation."""
    z = (coeffs - mean) / sigma
    return float((z * z).sum()), 2.0 * z / sigma


# ---------------------------------------------------------------------------------------------
# mesh topology
# ---------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class MeshTopology:
    """Connectivity of a triangle mesh, shared by the mesh regularisers (arrays read-only).

    n_vertices: V.
    edges: (E, 2) int64, each undirected edge once, ``edges[:, 0] < edges[:, 1]``.
    degree: (V,) int64, number of distinct neighbours of each vertex (0 if in no face).
    interior: (I, 4) int64 rows ``(v0, v1, a, b)`` for each edge shared by exactly two faces:
        the edge's endpoints and the vertices opposite it in the two faces. Boundary edges (one
        face) and non-manifold edges (three or more faces) are not listed.
    """
    n_vertices: int
    edges: np.ndarray
    degree: np.ndarray
    interior: np.ndarray


_TOPOLOGY_CACHE: OrderedDict = OrderedDict()
_TOPOLOGY_CACHE_SIZE = 16


def sh_white(coeffs) -> tuple[float, dict]:
    """Keeps spherical-harmonic light near white: the spread of each SH coefficient over the
    colour channels, ``sum_i sum_c (L[c, i] - mean_c L[c, i])**2``.

    ``coeffs``: (3, 9) SH coefficients (channel, basis). Zero for any grey light, whatever its
    brightness or direction; so the albedo, not the light, explains the colour of the skin.
    Returns ``(value, {"coeffs": (3, 9) gradient})``.
    """
    c = real_array("coeffs", coeffs)
    if c.shape != (3, 9):
        raise ValueError(f"coeffs: expected SH coefficients of shape (3, 9), got {c.shape}")
    d = c - c.mean(axis=0, keepdims=True)
    return float((d * d).sum()), {"coeffs": 2.0 * d}


def _faces(faces, n_vertices: int) -> np.ndarray:
    """(F, 3) integer faces -> int64, indices in [0, n_vertices), no face repeating a vertex."""
    f = index_array("faces", faces, n_vertices, shape=(None, 3), expected="(F, 3)")
    if f.size:
        rep = (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 2] == f[:, 0])
        if rep.any():
            raise ValueError(f"faces: face {int(np.argmax(rep))} repeats a vertex index "
                             f"{f[np.argmax(rep)].tolist()}")
    return f


def _build_topology(f: np.ndarray, n_vertices: int) -> MeshTopology:
    # Half-edges (i, j) of every face with the vertex opposite them.
    start = np.concatenate([f[:, 0], f[:, 1], f[:, 2]])
    end = np.concatenate([f[:, 1], f[:, 2], f[:, 0]])
    opposite = np.concatenate([f[:, 2], f[:, 0], f[:, 1]])
    lo, hi = np.minimum(start, end), np.maximum(start, end)
    key = lo * np.int64(max(n_vertices, 1)) + hi
    uniq, inverse, counts = np.unique(key, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    edges = np.stack([uniq // max(n_vertices, 1), uniq % max(n_vertices, 1)], axis=1)
    degree = np.bincount(edges.reshape(-1), minlength=n_vertices).astype(np.int64)
    order = np.argsort(inverse, kind="stable")          # half-edges grouped by undirected edge
    first = np.cumsum(counts) - counts
    inner = np.flatnonzero(counts == 2)
    h1, h2 = order[first[inner]], order[first[inner] + 1]
    interior = np.stack([edges[inner, 0], edges[inner, 1], opposite[h1], opposite[h2]], axis=1)
    edges, interior = edges.reshape(-1, 2), interior.reshape(-1, 4)
    for a in (edges, degree, interior):
        a.flags.writeable = False
    return MeshTopology(int(n_vertices), edges, degree, interior)


def mesh_topology(faces, n_vertices: int) -> MeshTopology:
    """Topology of ``faces`` (F, 3) integer indices into ``n_vertices`` vertices (cached).

    The cache holds the last few distinct face arrays (keyed by their content), so a fit that
    calls the mesh losses each iteration with the same faces builds it once.
    """
    n_vertices = int(n_vertices)
    f = _faces(faces, n_vertices)
    f = np.ascontiguousarray(f)
    key = (n_vertices, f.shape, hashlib.blake2b(f.tobytes(), digest_size=16).digest())
    topo = _TOPOLOGY_CACHE.get(key)
    if topo is None:
        topo = _build_topology(f, n_vertices)
        _TOPOLOGY_CACHE[key] = topo
        while len(_TOPOLOGY_CACHE) > _TOPOLOGY_CACHE_SIZE:
            _TOPOLOGY_CACHE.popitem(last=False)
    else:
        _TOPOLOGY_CACHE.move_to_end(key)
    return topo


def _mesh(vertices, faces) -> tuple[np.ndarray, MeshTopology]:
    v = real_array("vertices", vertices)
    if v.ndim != 2 or v.shape[1] != 3:
        raise ValueError(f"vertices: expected shape (V, 3), got {v.shape}")
    if isinstance(faces, MeshTopology):
        if faces.n_vertices != len(v):
            raise ValueError(f"faces: topology is for {faces.n_vertices} vertices, "
                             f"vertices has {len(v)}")
        return v, faces
    return v, mesh_topology(faces, len(v))


def _scatter(index: np.ndarray, values: np.ndarray, n: int) -> np.ndarray:
    """``out[index[k]] += values[k]`` for (K, 3) values into an (n, 3) array."""
    out = np.empty((n, values.shape[1]))
    for c in range(values.shape[1]):
        out[:, c] = np.bincount(index, weights=values[:, c], minlength=n)
    return out


def _neighbour_sum(x: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """``sum_{j in N(i)} x_j`` for every vertex i (x (V, 3))."""
    i, j = edges[:, 0], edges[:, 1]
    return _scatter(np.concatenate([i, j]), np.concatenate([x[j], x[i]]), len(x))


# ---------------------------------------------------------------------------------------------
# mesh regularisers
# ---------------------------------------------------------------------------------------------

def laplacian_coordinates(vertices, faces) -> np.ndarray:
    """Uniform Laplacian coordinates ``delta_i = v_i - mean_{j in N(i)} v_j``, (V, 3).

    ``N(i)``: the distinct vertices sharing a mesh edge with i. A vertex in no face has
    ``delta = 0``. ``faces`` may also be a :class:`MeshTopology`.
    """
    v, topo = _mesh(vertices, faces)
    return _delta(v, topo)[0]


def _delta(v: np.ndarray, topo: MeshTopology) -> tuple[np.ndarray, np.ndarray]:
    deg = topo.degree
    inv_deg = np.divide(1.0, deg, out=np.zeros(len(v)), where=deg > 0)
    delta = v - _neighbour_sum(v, topo.edges) * inv_deg[:, None]
    delta[deg == 0] = 0.0
    return delta, inv_deg


def laplacian(vertices, faces) -> tuple[float, dict]:
    """Uniform-Laplacian smoothness: ``sum_i |v_i - mean_{j in N(i)} v_j|^2``.

    ``vertices`` (V, 3) float (differentiable); ``faces`` (F, 3) integer indices (or a
    :class:`MeshTopology`); neighbours from the mesh's unique edges (see
    :func:`laplacian_coordinates`). With ``delta = L v``, ``L = I - D^-1 A``, the gradient is
    ``2 L^T delta = 2 (delta_i - sum_{j in N(i)} delta_j / deg_j)``.
    Returns ``(value, {"vertices": (V, 3)})``.
    """
    v, topo = _mesh(vertices, faces)
    delta, inv_deg = _delta(v, topo)
    grad = 2.0 * (delta - _neighbour_sum(delta * inv_deg[:, None], topo.edges))
    return float((delta * delta).sum()), {"vertices": grad}


def flatten(vertices, faces, eps: float = 1e-12) -> tuple[float, dict]:
    """Flatten regulariser: ``sum over interior edges of (cos(phi) + 1)^2``.

    For each edge (v0, v1) shared by exactly two faces, with opposite vertices a and b
    (see :class:`MeshTopology`; boundary and non-manifold edges contribute nothing):
    ``e = v1 - v0``, ``u_a`` = component of ``a - v0`` perpendicular to e, ``u_b`` likewise,
    ``cos(phi) = u_a . u_b / (|u_a| |u_b|)``; phi is the interior angle between the two faces
    at the edge (pi for a flat surface, giving 0; 4 for a face folded onto its neighbour). It
    does not depend on face orientation.

    Zero lengths are guarded with ``eps`` (squared-length units, > 0): the projection uses
    ``(p . e) / (e . e + eps)`` and the cosine ``u_a . u_b / sqrt((|u_a|^2 + eps)(|u_b|^2 +
    eps))``, so degenerate edges or faces give finite values and gradients (a collinear
    opposite vertex gives cos = 0). The gradient returned is exact for this guarded formula.
    Returns ``(value, {"vertices": (V, 3)})``.
    """
    v, topo = _mesh(vertices, faces)
    eps = float(real_array("eps", eps))
    positive("eps", np.asarray(eps))
    i0, i1, ia, ib = topo.interior.T
    if len(i0) == 0:
        return 0.0, {"vertices": np.zeros_like(v)}
    x0 = v[i0]
    e = v[i1] - x0
    pa = v[ia] - x0
    pb = v[ib] - x0

    def dot(x, y):
        return np.einsum("ij,ij->i", x, y)

    ee = dot(e, e) + eps
    ta = dot(pa, e) / ee
    tb = dot(pb, e) / ee
    ua = pa - ta[:, None] * e
    ub = pb - tb[:, None] * e
    na = dot(ua, ua) + eps
    nb = dot(ub, ub) + eps
    den = np.sqrt(na * nb)
    d = dot(ua, ub)
    cos = d / den
    value = float(((cos + 1.0) ** 2).sum())

    # Backward pass through the expressions above.
    g_cos = 2.0 * (cos + 1.0)
    g_d = g_cos / den
    g_na = -0.5 * g_cos * cos / na
    g_nb = -0.5 * g_cos * cos / nb
    g_ua = g_d[:, None] * ub + (2.0 * g_na)[:, None] * ua
    g_ub = g_d[:, None] * ua + (2.0 * g_nb)[:, None] * ub
    g_ta = -dot(g_ua, e)
    g_tb = -dot(g_ub, e)
    g_pa = g_ua + (g_ta / ee)[:, None] * e
    g_pb = g_ub + (g_tb / ee)[:, None] * e
    g_ee = -(g_ta * ta + g_tb * tb) / ee
    g_e = (-ta[:, None] * g_ua - tb[:, None] * g_ub
           + (g_ta / ee)[:, None] * pa + (g_tb / ee)[:, None] * pb
           + (2.0 * g_ee)[:, None] * e)
    g_x0 = -(g_e + g_pa + g_pb)
    grad = _scatter(np.concatenate([i0, i1, ia, ib]),
                    np.concatenate([g_x0, g_e, g_pa, g_pb]), len(v))
    return value, {"vertices": grad}


def edge_length(vertices, faces) -> tuple[float, dict]:
    """Edge-length regulariser: ``sum over unique undirected edges (i, j) of |v_i - v_j|^2``.

    Each edge counts once however many faces share it. Returns ``(value, {"vertices": (V, 3)})``
    with gradient ``2 sum_{j in N(i)} (v_i - v_j)``.
    """
    v, topo = _mesh(vertices, faces)
    i, j = topo.edges[:, 0], topo.edges[:, 1]
    d = v[i] - v[j]
    grad = _scatter(np.concatenate([i, j]), np.concatenate([2.0 * d, -2.0 * d]), len(v))
    return float((d * d).sum()), {"vertices": grad}


# ---------------------------------------------------------------------------------------------
# combination
# ---------------------------------------------------------------------------------------------

def weighted_sum(terms: Mapping[str, tuple], weights: Mapping[str, float],
                 ) -> tuple[float, dict, dict]:
    """Combine loss terms with weights by name.

    ``terms``: name -> ``(value, grads)`` as returned by the losses above. ``weights``: name ->
    float >= 0. A term whose weight is 0 or which has no weight is skipped (its value and
    gradients are not even read). A positive weight naming a term absent from ``terms`` raises
    ValueError (a requested loss that was not computed); a negative or NaN weight too.

    Returns ``(total, grads, weighted)``: ``total = sum_k w_k value_k`` over the used terms;
    ``grads[key] = sum_k w_k grads_k[key]`` (arrays under the same key, e.g. several terms'
    ``"vertices"``, are summed and must have the same shape); ``weighted = {name: w_k value_k}``
    for the used terms only. NaN values or gradients are passed through (the solver reports
    them). The inputs are not modified.
    """
    for name, w in weights.items():
        try:
            wf = float(w)
        except (TypeError, ValueError):
            raise ValueError(f"weights[{name!r}]: not a number ({w!r})") from None
        if not wf >= 0.0 or not np.isfinite(wf):
            raise ValueError(f"weights[{name!r}]: must be finite and >= 0, got {w!r}")
        if wf > 0.0 and name not in terms:
            raise ValueError(f"weights[{name!r}]: positive weight but no such term "
                             f"(terms: {sorted(terms)})")
    total = 0.0
    grads: dict = {}
    owner: dict = {}
    weighted: dict = {}
    for name, term in terms.items():
        w = float(weights.get(name, 0.0))
        if w == 0.0:
            continue
        try:
            value, g = term
        except (TypeError, ValueError):
            raise ValueError(f"terms[{name!r}]: expected a (value, grads) pair") from None
        if not isinstance(g, Mapping):
            raise ValueError(f"terms[{name!r}]: grads must be a dict, got {type(g).__name__}")
        wv = w * float(value)
        weighted[name] = wv
        total += wv
        for key, arr in g.items():
            a = np.asarray(arr, dtype=np.float64)
            if key in grads:
                if grads[key].shape != a.shape:
                    raise ValueError(f"terms[{name!r}]: grads[{key!r}] shape {a.shape} does not "
                                     f"match shape {grads[key].shape} from term "
                                     f"{owner[key]!r}")
                grads[key] += w * a
            else:
                grads[key] = w * a           # a new array: the caller's is never modified
                owner[key] = name
    return float(total), grads, weighted
