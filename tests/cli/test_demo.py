"""`softras-cl demo`: renders the built-in icosphere to a PNG and says where it went."""
import matplotlib.image
import numpy as np

from softras_cl import cli


def test_demo_writes_png(tmp_path, capsys):
    out = tmp_path / "sub" / "demo.png"
    code = cli.main(["demo", "--out", str(out), "--size", "48", "--faces", "1",
                     "--sigma", "1e-4", "--gamma", "1e-3"])
    assert code == 0
    printed = capsys.readouterr().out
    assert str(out) in printed and " s" in printed
    assert out.is_file()
    image = matplotlib.image.imread(out)
    assert image.shape[:2] == (48, 48)
    rgb = image[..., :3]
    assert np.allclose(rgb[0, 0], 1.0) and np.allclose(rgb[-1, -1], 1.0)   # white page in the corners
    centre = rgb[24, 24]
    # the sphere's nearest point (unit normal (0, 0, 1) towards the camera, colour 0.5 + 0.5 n =
    # (0.5, 0.5, 1)): bluish, not the white page
    assert not np.allclose(centre, 1.0, atol=0.05), centre
    assert centre[2] > 0.9 and centre[0] < centre[2] - 0.1 and centre[1] < centre[2] - 0.1, centre


def test_demo_help_lists_options(run_cli):
    result = run_cli("demo", "--help")
    assert result.code == 0
    text = result.out
    for option in ("--out", "--size", "--faces", "--sigma", "--gamma"):
        assert option in text
