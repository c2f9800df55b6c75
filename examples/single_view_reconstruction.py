#!/usr/bin/env python
"""Single-view mesh reconstruction (paper sec. 5.2, at CPU scale) through softras_cl.torch.

    python examples/single_view_reconstruction.py                 # full run, about 30 min
    python examples/single_view_reconstruction.py --quick    # under a minute, out/single_view_quick

Data: examples/make_shapes_dataset.py (4 procedural categories, random views, cached under
--out). Model: a small CNN encoder and an MLP decoder that deform a 642-vertex icosphere (the
paper's template size) from one shaded image: per-vertex displacements plus a global
anisotropic scale and a translation. Loss (the paper's silhouette setting, eq. 15 without the
colour term): 1 - soft IoU of the silhouettes rendered by softras-cl from several of the shape's
views (its input view among them) + Laplacian + flatten regularisers; Adam. Evaluation on the
held-out shapes: voxel IoU (32^3 over [-1, 1]^3) per category of the prediction, of the template
sphere, and of nearest-neighbour retrieval of a training shape (by silhouette IoU against all
training images, and against every training shape rendered from the input's own camera).
Writes results.json (with provenance), figure.png, model.pt and the loss history to --out.
Needs PyTorch: pip install 'softras-cl[torch]'.
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch
from torch import nn

sys.path.insert(0, str(Path(__file__).resolve().parent))
import make_shapes_dataset as shapes  # noqa: E402

from softras_cl import RasterSettings  # noqa: E402
from softras_cl.fitting.losses import mesh_topology  # noqa: E402
from softras_cl.io.outputs import atomic_path, write_figure, write_json  # noqa: E402
from softras_cl.provenance import provenance  # noqa: E402
from softras_cl.scene.meshes import icosphere  # noqa: E402
from softras_cl.torch import Renderer  # noqa: E402

TEMPLATE_RADIUS = 0.6


# ---------------------------------------------------------------------------------------------
# model
# ---------------------------------------------------------------------------------------------

class Encoder(nn.Module):
    """(B, 3, S, S) float32 image in [0, 1] -> (B, 512) float32 code; S a multiple of 16."""

    def __init__(self, size: int, width: int = 32):
        super().__init__()
        chans = [3, width, 2 * width, 4 * width, 8 * width]
        layers = []
        for a, b in zip(chans[:-1], chans[1:]):
            layers += [nn.Conv2d(a, b, 3, stride=2, padding=1), nn.BatchNorm2d(b), nn.ReLU()]
        self.conv = nn.Sequential(*layers)
        self.fc = nn.Sequential(nn.Flatten(), nn.Linear(chans[-1] * (size // 16) ** 2, 512),
                                nn.ReLU(), nn.Linear(512, 512), nn.ReLU())

    def forward(self, x):
        return self.fc(self.conv(x))


class Decoder(nn.Module):
    """(B, 512) code -> (B, V, 3) float32 vertices: s * (template + d) + t, with d per-vertex
    displacements, s a global anisotropic scale in (0.5, 1.5)^3, t a translation in (-0.2, 0.2)^3.
    Starts at the template (the output layer's weights are small)."""

    def __init__(self, template: np.ndarray):
        super().__init__()
        self.register_buffer("template", torch.as_tensor(template, dtype=torch.float32))
        n = 3 * len(template)
        self.mlp = nn.Sequential(nn.Linear(512, 1024), nn.ReLU())
        self.out = nn.Linear(1024, n + 6)
        with torch.no_grad():
            self.out.weight.mul_(0.01)
            self.out.bias.zero_()

    def forward(self, code):
        raw = self.out(self.mlp(code))
        d = 0.2 * raw[:, :-6].reshape(len(code), -1, 3)
        scale = 1.0 + 0.5 * torch.tanh(raw[:, -6:-3])
        shift = 0.2 * torch.tanh(raw[:, -3:])
        return scale[:, None] * (self.template + d) + shift[:, None]


class Reconstructor(nn.Module):
    """Image (B, 3, S, S) float32 -> vertices (B, V, 3) float32 of the deformed template."""

    def __init__(self, template: np.ndarray, size: int):
        super().__init__()
        self.encoder, self.decoder = Encoder(size), Decoder(template)

    def forward(self, images):
        return self.decoder(self.encoder(images))


# ---------------------------------------------------------------------------------------------
# losses
# ---------------------------------------------------------------------------------------------

def iou_loss(alpha: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Paper's silhouette loss 1 - |A*T|_1 / |A + T - A*T|_1 per image (N, H, W), averaged."""
    inter = (alpha * target).sum((1, 2))
    union = (alpha + target - alpha * target).sum((1, 2))
    return (1.0 - inter / union.clamp_min(1e-6)).mean()


class MeshRegularisers:
    """Laplacian and flatten terms of (B, V, 3) vertices on the template's topology.

    laplacian: sum_i |v_i - mean of its neighbours|^2 (uniform weights), averaged over B;
    flatten: sum over edges of (cos(phi) + 1)^2, phi the dihedral angle (pi when flat),
    averaged over B. Same definitions as softras_cl.fitting.losses, here in torch."""

    def __init__(self, faces: np.ndarray, n_vertices: int):
        topo = mesh_topology(np.asarray(faces), n_vertices)
        e = torch.tensor(np.asarray(topo.edges), dtype=torch.long)
        self.both = torch.cat([e, e.flip(1)])                    # (2E, 2) directed edges
        self.degree = torch.bincount(self.both[:, 0], minlength=n_vertices).float()[:, None]
        self.quads = torch.tensor(np.asarray(topo.interior), dtype=torch.long)   # (E, 4)

    def laplacian(self, v: torch.Tensor) -> torch.Tensor:
        total = torch.zeros_like(v).index_add_(1, self.both[:, 0], v[:, self.both[:, 1]])
        delta = v - total / self.degree
        return delta.square().sum((1, 2)).mean()

    def flatten(self, v: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
        i0, i1, ia, ib = self.quads.T
        x0 = v[:, i0]
        e = v[:, i1] - x0
        ee = (e * e).sum(-1, keepdim=True) + eps
        pa, pb = v[:, ia] - x0, v[:, ib] - x0
        ua = pa - (pa * e).sum(-1, keepdim=True) / ee * e
        ub = pb - (pb * e).sum(-1, keepdim=True) / ee * e
        cos = (ua * ub).sum(-1) / torch.sqrt(((ua * ua).sum(-1) + eps) * ((ub * ub).sum(-1) + eps))
        return (cos + 1.0).square().sum(1).mean()


# ---------------------------------------------------------------------------------------------
# training
# ---------------------------------------------------------------------------------------------

def as_input(images: np.ndarray) -> torch.Tensor:
    """uint8 images (N, S, S, 3) -> (N, 3, S, S) float32 in [0, 1]."""
    return torch.from_numpy(images).permute(0, 3, 1, 2).float().div(255.0)


def raster_settings(size: int, sigma64: float, gamma: float) -> RasterSettings:
    """Soft silhouettes for training: occupancy alpha, both face orientations, float32. sigma
    is given for 64x64 and scaled by (64 / size)^2 so that the blur covers the same fraction
    of a pixel at any size (sigma is a squared NDC distance)."""
    return RasterSettings(image_size=(size, size), sigma=sigma64 * (64.0 / size) ** 2, gamma=gamma,
                          outputs=("alpha",), alpha_agg="occupancy", double_sided=True)


def sample_batch(rng, train_idx, n_views, batch, views_per_step):
    """Shape indices (batch,), input view (batch,), supervising views (batch, k) (the input
    view first, then k - 1 other distinct views), all int64."""
    s = rng.choice(train_idx, batch, replace=len(train_idx) < batch)
    views = np.stack([rng.permutation(n_views)[:views_per_step] for _ in range(batch)])
    return s, views[:, 0], views


def train(model, data, template_faces, args, log=print) -> dict:
    """Adam on the silhouette loss; stops after args.steps or args.max_minutes. Returns the
    history: step, loss terms, seconds."""
    rng = np.random.default_rng(args.seed)
    size = data["images"].shape[2]
    train_idx = np.nonzero(~data["split"])[0]
    n_views = data["eyes"].shape[1]
    cams = {s: shapes.cameras(data["eyes"][s], size) for s in train_idx}
    renderer = Renderer(raster_settings(size, args.sigma, args.gamma), shading="none")
    reg = MeshRegularisers(template_faces, len(model.decoder.template))
    opt = torch.optim.Adam(model.parameters(), lr=args.lr, betas=(0.9, 0.999))
    history, t0 = [], time.perf_counter()
    model.train()
    for step in range(args.steps):
        s, inp, views = sample_batch(rng, train_idx, n_views, args.batch, args.views_per_step)
        verts = model(as_input(data["images"][s, inp]))                       # (B, V, 3)
        k = views.shape[1]
        target = torch.from_numpy(data["masks"][s[:, None], views].reshape(-1, size, size)).float()
        alpha = renderer(verts.repeat_interleave(k, 0), template_faces,
                         [cams[a][b] for a, row in zip(s, views) for b in row]).alpha
        terms = dict(iou=iou_loss(alpha, target), laplacian=reg.laplacian(verts),
                     flatten=reg.flatten(verts))
        loss = terms["iou"] + args.laplacian * terms["laplacian"] + args.flatten * terms["flatten"]
        opt.zero_grad()
        loss.backward()
        opt.step()
        elapsed = time.perf_counter() - t0
        if step % args.log_every == 0 or step == args.steps - 1:
            history.append(dict(step=step, seconds=elapsed, loss=loss.item(),
                                **{n: t.item() for n, t in terms.items()}))
            log(f"  step {step:5d}  {elapsed:7.1f} s  loss {loss.item():.4f}  "
                f"(1 - IoU {terms['iou'].item():.4f}, lap {terms['laplacian'].item():.3f}, "
                f"flat {terms['flatten'].item():.3f})")
        if elapsed > 60.0 * args.max_minutes:
            log(f"  stopped at step {step}: time limit of {args.max_minutes} min")
            break
    return dict(history=history, steps=step + 1, seconds=time.perf_counter() - t0)


# ---------------------------------------------------------------------------------------------
# evaluation
# ---------------------------------------------------------------------------------------------

def eval_inputs(data, views_per_shape: int):
    """Held-out (shape, view) pairs used as inputs: (shapes (N,), views (N,)) int64."""
    test_idx = np.nonzero(data["split"])[0]
    return np.repeat(test_idx, views_per_shape), np.tile(np.arange(views_per_shape), len(test_idx))


def mask_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Pairwise silhouette IoU of masks a (N, H, W) and b (M, H, W) bool -> (N, M) float64."""
    a = a.reshape(len(a), -1).astype(np.float32)
    b = b.reshape(len(b), -1).astype(np.float32)
    inter = a @ b.T
    union = a.sum(1)[:, None] + b.sum(1)[None] - inter
    return inter / np.maximum(union, 1.0)


def image_scores(data, masks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Training shapes (T,) int64 and, for input masks (N, H, W) bool, the best silhouette IoU
    (N, T) float32 of each against any of that shape's training images."""
    train_idx = np.nonzero(~data["split"])[0]
    pool = data["masks"][train_idx]                                  # (T, views, H, W)
    iou = mask_iou(masks, pool.reshape(-1, *pool.shape[2:]))
    return train_idx, iou.reshape(len(masks), len(train_idx), -1).max(-1)


def retrieve_by_image(data, masks: np.ndarray) -> np.ndarray:
    """For input masks (N, H, W) bool, the training shape (N,) int64 one of whose training
    images has the highest silhouette IoU with it (the network's information: the image only)."""
    train_idx, scores = image_scores(data, masks)
    return train_idx[np.argmax(scores, 1)]


def retrieve_by_view(data, masks: np.ndarray, eyes: np.ndarray, shortlist: int = 50) -> np.ndarray:
    """For input masks (N, H, W) bool seen from cameras at eyes (N, 3), the training shape (N,)
    int64 whose rendering from that same camera has the highest silhouette IoU with it: an
    oracle baseline, it knows the input's camera, which the network does not. Only the
    `shortlist` shapes with the best image scores (retrieve_by_image) are rendered per input."""
    size = masks.shape[1]
    renderer = shapes.silhouette_renderer(size)
    train_idx, scores = image_scores(data, masks)
    short = np.argsort(-scores, 1)[:, :shortlist]                  # (N, K) into train_idx
    best = np.full(scores.shape, -1.0)
    for t in np.unique(short):
        rows = np.nonzero((short == t).any(1))[0]
        v, f = shapes.mesh(data, train_idx[t])
        alpha = renderer.forward(v, f, shapes.cameras(eyes[rows], size)).alpha > 0.5
        m = masks[rows]
        best[rows, t] = (alpha & m).sum((1, 2)) / np.maximum((alpha | m).sum((1, 2)), 1)
    return train_idx[np.argmax(best, 1)]


def predict(model, images: np.ndarray, batch: int = 64) -> np.ndarray:
    """Predicted vertices (N, V, 3) float32 for uint8 images (N, S, S, 3)."""
    model.eval()
    with torch.no_grad():
        return np.concatenate([model(as_input(images[i:i + batch])).numpy()
                               for i in range(0, len(images), batch)])


def evaluate(model, data, template, args) -> dict:
    """Voxel IoU of every method on every held-out input: {method: (N,) float64}, plus the
    inputs, predictions and retrieved shapes for the figure."""
    s, views = eval_inputs(data, args.eval_views)
    images, masks, eyes = data["images"][s, views], data["masks"][s, views], data["eyes"][s, views]
    pred = predict(model, images)
    by_image = retrieve_by_image(data, masks)
    by_view = retrieve_by_view(data, masks, eyes)
    gt = data["voxels"][s]
    template_vox = shapes.voxelize(*template)
    iou = dict(prediction=[shapes.voxel_iou(shapes.voxelize(p, template[1]), g) for p, g in zip(pred, gt)],
               template=[shapes.voxel_iou(template_vox, g) for g in gt],
               retrieval_image=[shapes.voxel_iou(data["voxels"][r], g) for r, g in zip(by_image, gt)],
               retrieval_view=[shapes.voxel_iou(data["voxels"][r], g) for r, g in zip(by_view, gt)])
    return dict(iou={k: np.array(v) for k, v in iou.items()}, shapes=s, views=views, pred=pred,
                by_image=by_image, by_view=by_view)


METHODS = ("prediction", "template", "retrieval_image", "retrieval_view")


def table(data, ev) -> dict:
    """Mean voxel IoU per category and overall: {category: {method: float, "n": int}}."""
    cats = data["category"][ev["shapes"]]
    rows = {}
    for k, name in enumerate(shapes.CATEGORIES):
        sel = cats == k
        rows[name] = {m: float(ev["iou"][m][sel].mean()) for m in METHODS} | {"n": int(sel.sum())}
    rows["mean"] = {m: float(np.mean([rows[c][m] for c in shapes.CATEGORIES])) for m in METHODS} \
        | {"n": int(len(cats))}
    return rows


def markdown_table(rows: dict) -> str:
    """The per-category table as Markdown."""
    head = ("| category | inputs | prediction | template sphere | retrieval (image) "
            "| retrieval (known view) |\n|---|---:|---:|---:|---:|---:|\n")
    return head + "".join(f"| {c} | {r['n']} | " + " | ".join(f"{r[m]:.3f}" for m in METHODS)
                          + " |\n" for c, r in rows.items())


# ---------------------------------------------------------------------------------------------
# figure
# ---------------------------------------------------------------------------------------------

def shaded(vertices, faces, eye, size: int) -> np.ndarray:
    """(size, size, 3) uint8 image of a mesh from a camera at eye (3,), grey Lambert on white."""
    rgb, mask = shapes.render_views(vertices, faces, eye[None], size)
    return np.where(mask[0, ..., None], rgb[0], 255)


def novel_eye(eye: np.ndarray) -> np.ndarray:
    """The input camera turned 90 degrees about y, at 30 degrees elevation."""
    azim = np.arctan2(eye[0], eye[2]) + np.pi / 2
    el = np.radians(30.0)
    return shapes.CAMERA_DISTANCE * np.array([np.cos(el) * np.sin(azim), np.sin(el),
                                              np.cos(el) * np.cos(azim)])


def figure(data, ev, template_faces, rows_per_category: int, size: int = 96):
    """Rows: held-out inputs, rows_per_category per category; columns: input, then prediction,
    retrieval (image) and ground truth, each from the input camera and a novel one."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cats = data["category"][ev["shapes"]]
    picks = [i for k in range(len(shapes.CATEGORIES))
             for i in np.nonzero((cats == k) & (ev["views"] == 0))[0][:rows_per_category]]
    cols = ["input", "prediction", "(novel view)", "retrieval", "(novel view)", "ground truth",
            "(novel view)"]
    fig, axes = plt.subplots(len(picks), 7, figsize=(7 * 1.3, len(picks) * 1.3), squeeze=False)
    for row, i in enumerate(picks):
        s, view = ev["shapes"][i], ev["views"][i]
        eye = data["eyes"][s, view]
        meshes = [(ev["pred"][i], template_faces), shapes.mesh(data, ev["by_image"][i]),
                  shapes.mesh(data, s)]
        cells = [data["images"][s, view]] + [shaded(v, f, e, size) for v, f in meshes
                                             for e in (eye, novel_eye(eye))]
        for col, (ax, img) in enumerate(zip(axes[row], cells)):
            ax.imshow(img)
            ax.set_xticks([]), ax.set_yticks([])
            if row == 0:
                ax.set_title(cols[col], fontsize=8)
        axes[row, 0].set_ylabel(f"{shapes.CATEGORIES[cats[i]]}\nIoU {ev['iou']['prediction'][i]:.2f}",
                                fontsize=7)
    fig.tight_layout()
    return fig


# ---------------------------------------------------------------------------------------------
# main
# ---------------------------------------------------------------------------------------------

QUICK = dict(train=6, test=2, views=4, size=32, steps=8, batch=4, views_per_step=2, eval_views=1,
             rows=1, log_every=2)


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    add = p.add_argument
    add("--out", default=None, help="output folder, data set cache too (default: "
        "out/single_view, with --quick out/single_view_quick)")
    add("--quick", action="store_true", help="tiny data, few steps: a smoke test in seconds")
    add("--train", type=int, default=200, help="training shapes per category")
    add("--test", type=int, default=25, help="held-out shapes per category")
    add("--views", type=int, default=12, help="rendered views per shape")
    add("--size", type=int, default=64, help="image size (square, a multiple of 16)")
    add("--steps", type=int, default=4000, help="Adam steps (at most)")
    add("--max-minutes", type=float, default=25.0, help="stop training after this wall time")
    add("--batch", type=int, default=16, help="shapes per step")
    add("--views-per-step", type=int, default=3, help="silhouettes per shape per step")
    add("--lr", type=float, default=3e-4, help="Adam learning rate")
    add("--sigma", type=float, default=1e-4, help="sigma at 64x64 (scaled by (64/size)^2)")
    add("--gamma", type=float, default=1e-4)
    add("--laplacian", type=float, default=5e-3, help="Laplacian weight")
    add("--flatten", type=float, default=5e-4, help="flatten weight")
    add("--eval-views", type=int, default=2, help="input views per held-out shape")
    add("--rows", type=int, default=2, help="figure rows per category")
    add("--log-every", type=int, default=100)
    add("--seed", type=int, default=0)
    args = p.parse_args(argv)
    if args.out is None:
        args.out = "out/single_view_quick" if args.quick else "out/single_view"
    if args.quick:
        for k, v in QUICK.items():
            if p.get_default(k) == getattr(args, k):
                setattr(args, k, v)
    return args


def main(argv=None) -> int:
    args = parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(args.seed)
    load_start = os.getloadavg()
    data, data_path = shapes.load_or_make(out, args.train, args.test, args.views, args.size,
                                          args.seed, progress=True)
    print(f"data: {data_path} ({len(data['split'])} shapes)")
    template = icosphere(3, TEMPLATE_RADIUS)
    model = Reconstructor(template[0], args.size)
    run = train(model, data, template[1], args)
    print(f"trained {run['steps']} steps in {run['seconds']:.0f} s; evaluating")
    t0 = time.perf_counter()
    ev = evaluate(model, data, template, args)
    rows = table(data, ev)
    print(markdown_table(rows), end="")
    write_figure(figure(data, ev, template[1], args.rows), out / "figure.png", dpi=110)
    with atomic_path(out / "model.pt") as tmp:
        torch.save(model.state_dict(), tmp)
    write_json(out / "results.json", dict(
        table=rows, train_seconds=run["seconds"], steps=run["steps"],
        eval_seconds=time.perf_counter() - t0, history=run["history"],
        load_average=dict(start=load_start, end=os.getloadavg()), cpu_count=os.cpu_count(),
        torch=torch.__version__, torch_threads=torch.get_num_threads(), data=str(data_path),
        provenance=provenance(args)))
    print(f"wrote {out / 'results.json'}, {out / 'figure.png'}, {out / 'model.pt'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
