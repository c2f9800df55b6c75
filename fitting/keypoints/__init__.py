"""The keypoint formats the fits read, declared once as data: one module per format.

- ibug68: the iBUG 300-W 68 face landmarks (COUNT, the parts as ranges: JAW, BROWS, RIGHT_EYE,
  ..., CHIN, NOSE_TIP, OUTER_EYE_CORNERS, FACE_OUTLINE, OPENINGS, NAMES);
- face_mesh: MediaPipe Face Mesh's dense points (COUNT 468, WITH_IRISES 478) and MP468_TO_IBUG68,
  the mesh vertex that stands for each iBUG point;
- pose33: MediaPipe's 33 pose keypoints (NAMES, TORSO) and KEYPOINT_MAP, the body model's point
  that each stands for (keypoint_layout resolves it on a model);
- plausibility: whether 68 points can be a face's iBUG points (the check of the detectors and
  of the fits alike).

A neutral layer: detection, recipes, reports and the benchmarks import it; it imports numpy, the
standard library and softras_cl.errors only.
"""
