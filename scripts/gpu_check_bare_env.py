"""A Python environment holding only what the GPU machines' image holds, to rehearse
scripts/gpu_check.sh here (docs/gpu_check.md) and so prove that the carried wheels suffice.

    .venv/bin/python scripts/gpu_check_bare_env.py DIR

Makes a virtual environment in DIR (this Python's version, with pip) that sees, of this
environment's distributions, only those named in GPU_IMAGE_PACKAGES (the image's package list),
through symbolic links in DIR/image_site. softras-cl itself, pyopencl, PoCL, trimesh, nlopt and
pypng stay out, as on the GPU machine. Prints DIR/bin/python.
"""
from __future__ import annotations

import argparse
import re
import subprocess
import sys
import sysconfig
from importlib import metadata
from pathlib import Path

# The Python packages of the GPU machines' image ('cuda'), as listed for it on 2026-11-17.
GPU_IMAGE_PACKAGES = frozenset("""
absl-py accelerate aiofiles aiohappyeyeballs aiohttp aiosignal annotated-doc anyio attrs botorch
build certifi charset-normalizer chex click cloudpickle cmake colorama contourpy coverage
cuda-bindings cuda-core cuda-pathfinder cuda-toolkit cupy-cuda13x cycler cython diffrax e3nn einops
equinox etils execnet filelock flatbuffers flax fonttools formulaic frozenlist fsspec gpytorch grpcio
h11 h5py hf-xet httpcore httpx huggingface-hub humanize hypothesis idna imageio interface-meta iniconfig
jax jax-cuda13-pjrt jax-cuda13-plugin jaxlib jaxtyping jinja2 joblib kiwisolver lazy-loader lightning
lightning-utilities linear-operator lineax llvmlite lxml markdown markdown-it-py markupsafe matplotlib
mdurl meson ml-dtypes mpi4py mpmath msgpack multidict multipledispatch mypy-extensions nanobind narwhals
networkx ninja numba numba-cuda numpy numpyro nvidia-cublas nvidia-cuda-cupti nvidia-cuda-nvrtc
nvidia-cuda-runtime nvidia-cudnn-cu13 nvidia-cufft nvidia-cufile nvidia-curand nvidia-cusolver
nvidia-cusparse nvidia-cusparselt-cu13 nvidia-ml-py nvidia-nccl-cu13 nvidia-nvjitlink
nvidia-nvshmem-cu13 nvidia-nvtx onnx onnx-ir onnxruntime onnxscript opencv-python-headless optax
opt-einsum opt-einsum-fx optimistix orbax-checkpoint packaging pandas pathspec patsy peft pillow pip
pluggy portalocker prometheus-client propcache protobuf psutil pyarrow pybind11 py-cpuinfo pygments
pyparsing pyproject-hooks pyre-extensions pytest pytest-benchmark pytest-cov pytest-mock
pytest-timeout pytest-xdist python-dateutil pytorch-lightning pyyaml regex requests rich sacrebleu
safetensors scikit-build-core scikit-image scikit-learn scipy seaborn sentencepiece
sentence-transformers setuptools shellingham simplejson six sortedcontainers statsmodels sympy
tabulate tensorboard tensorboard-data-server tensorstore threadpoolctl tifffile tiktoken timm
tokenizers toolz torch torchaudio torchdiffeq torch-geometric torchmetrics torchvision tqdm
transformers treescope triton typer typing-extensions typing-inspect urllib3 uvloop wadler-lindig
werkzeug wheel wrapt xarray xxhash yarl zipp
""".split())


def normalized(name: str) -> str:
    """A distribution name as package indexes compare them: 'Typing_Extensions' -> 'typing-extensions'."""
    return re.sub(r"[-_.]+", "-", name).lower()


def top_level_entries(dist: metadata.Distribution) -> set[str]:
    """First path parts of a distribution's installed files inside site-packages (packages,
    modules, .libs folders, its .dist-info), leaving out scripts and data installed elsewhere."""
    return {Path(f).parts[0] for f in dist.files or () if not str(f).startswith("..")}


def image_distributions(dists) -> list[metadata.Distribution]:
    """The distributions of `dists` that the GPU image also holds, one per name."""
    chosen = {}
    for dist in dists:
        name = normalized(dist.metadata["Name"] or "")
        if name in GPU_IMAGE_PACKAGES:
            chosen.setdefault(name, dist)
    return list(chosen.values())


def link_site(site: Path, dists, target: Path) -> int:
    """Symbolic links in `target` to the top-level entries (in folder `site`) of `dists`;
    returns how many were made."""
    target.mkdir(parents=True, exist_ok=True)
    made = 0
    for dist in dists:
        for entry in top_level_entries(dist):
            source, link = site / entry, target / entry
            if source.exists() and not link.exists():
                link.symlink_to(source)
                made += 1
    return made


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("dir", type=Path, help="folder for the new environment (must not exist)")
    args = p.parse_args(argv)
    if args.dir.exists():
        p.error(f"{args.dir} exists already: give a new folder")
    site = Path(sysconfig.get_paths()["purelib"])
    subprocess.run([sys.executable, "-m", "venv", str(args.dir)], check=True)
    dists = image_distributions(metadata.distributions(path=[str(site)]))
    made = link_site(site, dists, args.dir / "image_site")
    new_site = subprocess.run([str(args.dir / "bin" / "python"), "-c",
                               "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                              check=True, capture_output=True, text=True).stdout.strip()
    (Path(new_site) / "gpu_image.pth").write_text(str(args.dir / "image_site") + "\n")
    print(f"{len(dists)} distributions ({made} entries) linked; python: {args.dir / 'bin' / 'python'}",
          file=sys.stderr)
    print(args.dir / "bin" / "python")
    return 0


if __name__ == "__main__":
    sys.exit(main())
