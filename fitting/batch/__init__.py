"""Many fits at once, on a Dask cluster or one after the other.

- items: the items of a batch (photos, targets or videos from paths, folders, globs and CSV
  manifests), plain data sent to the workers;
- tasks: one item's task on a worker (its job from fitting.jobs, skip when finished, publish its
  folder whole);
- client: fit_many, the client side (submit, collect rows, Ctrl-C);
- cluster: the local cluster and its workers' threads;
- results: results.csv, results.jsonl and summary.png;
- videos: track-face on several videos.
"""
