"""bench body's summary: CPU time per fit beside the wall time (no fitting here; the command
itself runs in tests/cli/test_body_cli.py)."""
from softras_cl.bench.body import format_table, summarise


def _row(seconds, cpu, iou=0.9):
    return dict(mpjpe_mm=100.0, mpjpe_pelvis_mm=80.0, silhouette_iou=iou, seconds=seconds,
                cpu_seconds=cpu, evaluations=300)


def test_summary_and_table_report_median_cpu_seconds():
    summary = summarise([_row(10.0, 7.0), _row(30.0, 9.0, 0.8), _row(20.0, 8.5)])
    assert summary["median_seconds"] == 20.0 and summary["median_cpu_seconds"] == 8.5
    assert summary["silhouette_iou_min"] == 0.8
    table = format_table({"default": summary}, dict(mpjpe_pelvis_mm=150.0, silhouette_iou=0.5))
    head, rest, row = table.splitlines()
    assert head.rstrip().endswith("CPU s/fit")
    assert row.split()[-2:] == ["20.0", "8.5"]
