"""The OpenCL layer: device choice (`device`), kernel sources (`source`) and program building
with -D flags, cached per context (`program`)."""
