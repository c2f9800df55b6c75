"""One job per data path: read the inputs once, resolve the landmarks, the person or the frames,
run a recipe, write through fitting.reports.

- face_photo: a face from a photo (FacePhotoJob) or from several photos of one person
  (FaceViewsJob);
- face_video: a face tracked through a video (track_video);
- body_photo: a body from a photo of a person (BodyPhotoJob);
- body_target: a body from a renderer-made target image, with optional 2D joints (BodyTargetJob);
  body.body_job chooses between the two body jobs;
- run: one fit job into one output folder (run_fit; fit_and_write, shared with a batch task).

The command line (softras_cl.cli) and the Dask tasks (fitting.batch) call these and nothing
below them; the recipes below import neither detection nor file I/O.
"""
