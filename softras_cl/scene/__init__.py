"""From a world-space mesh to the rasteriser's screen space: rotations, cameras, shading
(Lambert, Phong, spherical harmonics), the differentiable renderer and primitive meshes."""
