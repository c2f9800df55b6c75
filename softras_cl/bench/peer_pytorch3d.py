"""Peer worker of `softras-cl bench peers`: PyTorch3D's CPU soft rasteriser on a scene file.

Run with the peer environment's Python (scripts/setup_peers.sh), not imported by softras-cl: it
needs only numpy, torch and pytorch3d. Usage: ``python peer_pytorch3d.py SCENE.npz OUT.npz THREADS``
(THREADS: torch's intra-op threads, set explicitly so that no inherited MKL_NUM_THREADS=1 decides).

Protocol (softras_cl/bench/peers.py is the other side): the worker reads the scene, which is in
softras-cl's conventions (docs/conventions.md), picks faces_per_pixel and prints ``ready K``.
Each ``run`` line on stdin makes one forward (with the autograd graph) and one backward of
sum(rgb * grad_rgb) + sum(alpha * grad_alpha) and prints ``done FWD FWDBWD FWD_CPU FWDBWD_CPU``
(seconds, wall and process CPU). ``quit`` (or end of input) writes OUT.npz with the last run's
rgb (H, W, 3), alpha (H, W), grad_vertices (V, 3) (all float64 copies of float32 results), the
gradient of the alpha term alone (grad_silhouette), the pixels where the two barycentric clippings
differ (clipping_differs, (H, W) bool), the number of pixel-face pairs kept, the pixels whose K
slots were all filled, and ``info`` (JSON).

Mapping of softras-cl's soft rasteriser onto PyTorch3D's (the function computed is the same, see
docs/bench/peers.md for the derivation):
- PyTorch3D's NDC +X points left and the pixel centres are otherwise ours, so x is negated; that
  turns our counter-clockwise front faces clockwise, which is what PyTorch3D's cull_backfaces
  keeps (its face area has the opposite sign), so cull_backfaces = not double_sided;
- squared distances are in NDC on both sides: sigma and gamma are the same numbers, and our
  cut-off D >= dist_eps for outside pixels, sigmoid(-d2 / sigma) >= dist_eps, is
  d2 <= sigma * log(1 / dist_eps - 1) = blur_radius (PyTorch3D keeps d2 < blur_radius);
- clip_barycentric_coords=True and perspective correction give our clipped depth and colour
  weights wherever no screen-space barycentric coordinate exceeds 1 (PyTorch3D clamps only the
  negative ones, softras-cl clips to [0, 1]: the one difference, reported per pixel); znear / zfar of softmax_rgb_blend are our near / far, whose clipping never acts here
  because every vertex depth is checked to lie in [near, far];
- PyTorch3D keeps the K nearest faces per pixel: K doubles from 8 until no pixel fills all K
  slots, so no pair inside the cut-off is dropped.
"""
from __future__ import annotations

import json
import math
import os
import platform
import sys
import time

FIRST_K = 8


def load_scene(path):
    """The scene arrays and settings written by peers.export_scene (a dict)."""
    import numpy as np

    with np.load(path) as data:
        return {k: data[k] for k in data.files}


def check_scene(scene) -> None:
    """Refuse what PyTorch3D cannot compute the same way (ValueError naming the field)."""
    z = scene["vertices"][:, 2]
    if not (z.min() >= float(scene["near"]) and z.max() <= float(scene["far"])):
        raise ValueError(f"vertices: depths {z.min():g}..{z.max():g} leave [near, far] = "
                         f"[{float(scene['near']):g}, {float(scene['far']):g}]; PyTorch3D does not clip there")
    if not 0 < float(scene["dist_eps"]) < 0.5:
        raise ValueError(f"dist_eps: PyTorch3D needs a finite blur radius, i.e. 0 < dist_eps < 0.5, "
                         f"got {float(scene['dist_eps'])}")


def blur_radius(sigma: float, dist_eps: float) -> float:
    """PyTorch3D's blur_radius (a squared NDC distance) for our cut-off: outside a face,
    D = sigmoid(-d2 / sigma) >= dist_eps exactly when d2 <= sigma * log(1 / dist_eps - 1)."""
    return sigma * math.log(1.0 / dist_eps - 1.0)


class Peer:
    """PyTorch3D set up for one scene: tensors, the mapped settings and the renderer."""

    def __init__(self, scene):
        import torch
        from pytorch3d.renderer.blending import BlendParams

        check_scene(scene)
        self.scene = scene
        self.torch = torch
        self.vertices = torch.tensor(scene["vertices"], dtype=torch.float32)
        self.faces = torch.tensor(scene["faces"], dtype=torch.int64)
        self.colors = torch.tensor(scene["colors"], dtype=torch.float32)
        self.grad_rgb = torch.tensor(scene["grad_rgb"], dtype=torch.float32).reshape(1, *scene["grad_rgb"].shape[-3:])
        self.grad_alpha = torch.tensor(scene["grad_alpha"], dtype=torch.float32).reshape(1, *scene["grad_alpha"].shape[-2:])
        self.flip = torch.tensor([-1.0, 1.0, 1.0])
        sigma = float(scene["sigma"])
        self.blur_radius = blur_radius(sigma, float(scene["dist_eps"]))
        self.blend = BlendParams(sigma=sigma, gamma=float(scene["gamma"]),
                                 background_color=tuple(float(c) for c in scene["background"]))
        self.k = int(scene["faces_per_pixel"]) or self.enough_k()
        self.last = None

    def rasterize(self, vertices, k: int):
        """PyTorch3D fragments of our-convention vertices (V, 3) with K = k faces per pixel."""
        from pytorch3d.renderer.mesh.rasterize_meshes import rasterize_meshes
        from pytorch3d.renderer.mesh.rasterizer import Fragments
        from pytorch3d.structures import Meshes

        mesh = Meshes(verts=[vertices * self.flip], faces=[self.faces])
        height, width = (int(n) for n in self.scene["size"])
        out = rasterize_meshes(mesh, image_size=(height, width), blur_radius=self.blur_radius,
                               faces_per_pixel=k, bin_size=0, perspective_correct=bool(self.scene["perspective_correct"]),
                               clip_barycentric_coords=True, cull_backfaces=not bool(self.scene["double_sided"]))
        return Fragments(*out)

    def enough_k(self) -> int:
        """Smallest K = 8 * 2**n at which no pixel fills all K slots (forward-only rasterisations)."""
        k = FIRST_K
        with self.torch.no_grad():
            while int((self.rasterize(self.vertices, k).pix_to_face[..., -1] >= 0).sum()):
                k *= 2
        return k

    def forward(self, vertices):
        """(rgb (1, H, W, 3), alpha (1, H, W), fragments) of the soft rasteriser."""
        from pytorch3d.ops import interpolate_face_attributes
        from pytorch3d.renderer.blending import softmax_rgb_blend

        frags = self.rasterize(vertices, self.k)
        colors = interpolate_face_attributes(frags.pix_to_face, frags.bary_coords, self.colors[self.faces])
        rgba = softmax_rgb_blend(colors, frags, self.blend, znear=float(self.scene["near"]),
                                 zfar=float(self.scene["far"]))
        return rgba[..., :3], rgba[..., 3], frags

    def run(self) -> tuple[float, float, float, float]:
        """One timed forward + backward: (fwd s, fwd+bwd s, fwd CPU s, fwd+bwd CPU s)."""
        vertices = self.vertices.clone().requires_grad_(True)
        t0, c0 = time.perf_counter(), time.process_time()
        rgb, alpha, frags = self.forward(vertices)
        t1, c1 = time.perf_counter(), time.process_time()
        ((rgb * self.grad_rgb).sum() + (alpha * self.grad_alpha).sum()).backward()
        t2, c2 = time.perf_counter(), time.process_time()
        self.last = (rgb, alpha, frags, vertices.grad)
        return t1 - t0, t2 - t0, c1 - c0, c2 - c0

    def silhouette_gradient(self):
        """dL/d(vertices) (V, 3) of L = sum(alpha * grad_alpha) alone: alpha does not involve the
        barycentric clipping, so this gradient is the same function on both sides."""
        vertices = self.vertices.clone().requires_grad_(True)
        _, alpha, _ = self.forward(vertices)
        (alpha * self.grad_alpha).sum().backward()
        return vertices.grad

    def clipping_differs(self, frags):
        """(H, W) bool: pixels with a kept pair whose screen-space barycentrics b have a
        coordinate > 1. There PyTorch3D's clipping (negatives to 0, then normalise) and
        softras-cl's (clip to [0, 1], then normalise) give different colour and depth weights."""
        torch = self.torch
        height, width = (int(n) for n in self.scene["size"])
        n, rows, cols, k = torch.nonzero(frags.pix_to_face >= 0, as_tuple=True)
        tri = self.vertices.double()[self.faces[frags.pix_to_face[n, rows, cols, k]]]    # (P, 3, 3)
        short = min(height, width)
        px, py = (2.0 * (cols + 0.5) - width) / short, (height - 2.0 * (rows + 0.5)) / short
        x, y = tri[..., 0], tri[..., 1]
        area = (x[:, 1] - x[:, 0]) * (y[:, 2] - y[:, 0]) - (x[:, 2] - x[:, 0]) * (y[:, 1] - y[:, 0])
        b = torch.stack([((x[:, i] - px) * (y[:, j] - py) - (x[:, j] - px) * (y[:, i] - py)) / area
                         for i, j in ((1, 2), (2, 0), (0, 1))], -1)
        over = b.max(-1).values > 1
        differs = torch.zeros((height, width), dtype=torch.bool)
        differs[rows[over], cols[over]] = True
        return differs

    def save(self, path) -> None:
        """Write the last run's images, gradients and counts, the silhouette gradient, the
        clipping mask and `info` to `path` (.npz)."""
        import numpy as np

        rgb, alpha, frags, grad = self.last
        kept = frags.pix_to_face >= 0
        np.savez(path, rgb=rgb[0].detach().double().numpy(), alpha=alpha[0].detach().double().numpy(),
                 grad_vertices=grad.double().numpy(), grad_silhouette=self.silhouette_gradient().double().numpy(),
                 clipping_differs=self.clipping_differs(frags).numpy(), pairs=int(kept.sum()),
                 saturated_pixels=int(kept[..., -1].sum()), info=json.dumps(info(self.k, self.blur_radius)))


def cpu_model() -> str | None:
    """/proc/cpuinfo's model name (None elsewhere)."""
    try:
        with open("/proc/cpuinfo") as f:
            return next((line.split(":", 1)[1].strip() for line in f if line.startswith("model name")), None)
    except OSError:
        return None


def info(k: int, blur_radius: float) -> dict:
    """Provenance of the peer side: versions, threads, CPU, and the mapped settings."""
    import numpy
    import pytorch3d
    import torch

    return dict(renderer="pytorch3d", pytorch3d=pytorch3d.__version__, torch=torch.__version__,
                torch_cuda_build=torch.version.cuda, numpy=numpy.__version__, python=platform.python_version(),
                threads=torch.get_num_threads(), interop_threads=torch.get_num_interop_threads(),
                omp_num_threads=os.environ.get("OMP_NUM_THREADS"), cpu=cpu_model(), os=platform.platform(),
                executable=sys.executable, faces_per_pixel=k, blur_radius=blur_radius, bin_size=0,
                clip_barycentric_coords=True)


def serve(scene_path: str, out_path: str, threads: int) -> int:
    """The stdin/stdout protocol of the module docstring, torch on `threads` threads."""
    import torch

    torch.set_num_threads(threads)
    peer = Peer(load_scene(scene_path))
    print(f"ready {peer.k}", flush=True)
    for line in sys.stdin:
        command = line.strip()
        if command == "quit":
            break
        if command != "run":
            raise ValueError(f"unknown command {command!r} (expected run or quit)")
        print("done " + " ".join(f"{t:.9f}" for t in peer.run()), flush=True)
    if peer.last is None:
        raise ValueError("quit before any run: nothing to write")
    peer.save(out_path)
    return 0


if __name__ == "__main__":
    if len(sys.argv) != 4:
        sys.exit("usage: peer_pytorch3d.py SCENE.npz OUT.npz THREADS")
    sys.exit(serve(sys.argv[1], sys.argv[2], int(sys.argv[3])))
