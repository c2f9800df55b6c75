"""fit-face's focal length: --focal fixes it, else --fov starts it and centres its prior, else a
photo's EXIF 35 mm equivalent focal length does, else the typical 30 degree field of view does
(fitting.jobs.face_photo.with_focal_prior)."""
import math

import pytest

from softras_cl.errors import InputError
from softras_cl.fitting.jobs.face_photo import FacePhotoJob, FaceViewsJob, exif_focal, with_focal_prior
from softras_cl.fitting.recipes.face_settings import FaceFitConfig


def _photos(tmp_path, size=(300, 200), focal_35mm=50):
    from PIL import Image

    image = Image.new("RGB", size, (128, 110, 100))
    exif = image.getexif()
    exif.get_ifd(0x8769)[41989] = focal_35mm
    image.save(tmp_path / "exif.jpg", exif=exif)
    image.save(tmp_path / "plain.jpg")
    return tmp_path / "exif.jpg", tmp_path / "plain.jpg"


def test_exif_focal_is_the_35mm_equivalent_in_pixels(tmp_path):
    """50 mm on the 43.27 mm diagonal of a 36 x 24 mm frame: focal in pixels = 50 / 43.27 x the
    photo's diagonal in pixels; the field of view is across the longer side."""
    with_exif, plain = _photos(tmp_path)
    focal, fov = exif_focal(with_exif, (200, 300))
    assert focal == pytest.approx(50 / 43.27 * math.hypot(200, 300), rel=1e-9)
    assert fov == pytest.approx(math.degrees(2 * math.atan(150 / focal)), rel=1e-12)
    assert exif_focal(plain, (200, 300)) is None


def test_focal_given_beats_fov_beats_exif_beats_the_prior(tmp_path):
    with_exif, plain = _photos(tmp_path)
    config = FaceFitConfig()
    given = FaceFitConfig(focal=400.0)
    assert with_focal_prior(given, 60.0, with_exif, (200, 300)) == (given, "--focal")      # --focal wins
    assert with_focal_prior(config, None, plain, (200, 300)) == (config, "prior")          # the 30 degrees
    exif_config, source = with_focal_prior(config, None, with_exif, (200, 300))
    assert source == "exif" and exif_config.focal is None
    assert exif_config.fov_deg == pytest.approx(exif_focal(with_exif, (200, 300))[1])
    # the fit starts at and centres its prior on that focal length (prepare_fit's fov_deg focal)
    start = 0.5 * 300 / math.tan(math.radians(exif_config.fov_deg) / 2)
    assert start == pytest.approx(exif_focal(with_exif, (200, 300))[0], rel=1e-9)
    for photo in (with_exif, plain):               # --fov beats the EXIF
        fov_config, source = with_focal_prior(config, 60.0, photo, (200, 300))
        start = 0.5 * 300 / math.tan(math.radians(fov_config.fov_deg) / 2)
        assert source == "--fov" and start == pytest.approx(0.5 * 200 / math.tan(math.radians(30.0)), rel=1e-12)


@pytest.mark.parametrize("options, says", [
    (dict(fov=0.0), "--fov must be a field of view in degrees"),
    (dict(fov=180.0), "--fov must be a field of view in degrees"),
    (dict(fov=float("nan")), "--fov must be a field of view in degrees"),
])
def test_a_bad_fov_is_refused_before_the_photo_is_read(tmp_path, options, says):
    with pytest.raises(InputError, match=says):
        FacePhotoJob(tmp_path / "missing.png", None, options)


def test_fov_is_a_single_photos_option(tmp_path):
    with pytest.raises(InputError, match="--fov is a single photo's"):
        FaceViewsJob([tmp_path / "a.png", tmp_path / "b.png"], None, dict(fov=50.0))


def test_fit_face_cli_refuses_a_bad_fov_with_exit_2(run_cli, examples_data, tmp_path):
    result = run_cli("fit-face", examples_data / "astronaut.png", "--fov", "200", "--out", tmp_path / "out")
    assert result.code == 2 and "--fov must be a field of view in degrees" in result.err
    assert not (tmp_path / "out").exists()
    assert "--fov DEG" in run_cli("fit-face", "--help").out


def test_a_face_job_reads_the_exif_focal(tmp_path, examples_data, examples_landmarks):
    """FacePhotoJob.read takes the EXIF focal length into its config (and says so) unless
    --focal or --fov is given (--focal wins over both); a photo without EXIF keeps the config's
    30 degrees."""
    from PIL import Image

    with Image.open(examples_data / "astronaut.png") as image:
        image = image.convert("RGB")
        exif = image.getexif()
        exif.get_ifd(0x8769)[41989] = 85
        image.save(tmp_path / "exif.jpg", exif=exif, quality=95)
        image.save(tmp_path / "plain.jpg", quality=95)
    points = examples_landmarks / "astronaut.pts"
    job = FacePhotoJob(tmp_path / "exif.jpg", points, dict(size=64))
    job.read()
    assert job.focal_source == "exif"
    assert job.config.fov_deg == pytest.approx(exif_focal(tmp_path / "exif.jpg", (512, 512))[1])
    job = FacePhotoJob(tmp_path / "exif.jpg", points, dict(size=64, focal=700.0))
    job.read()
    assert (job.focal_source, job.config.focal, job.config.fov_deg) == ("--focal", 700.0, FaceFitConfig().fov_deg)
    job = FacePhotoJob(tmp_path / "plain.jpg", points, dict(size=64))
    job.read()
    assert (job.focal_source, job.config.fov_deg) == ("prior", FaceFitConfig().fov_deg)
    job = FacePhotoJob(tmp_path / "exif.jpg", points, dict(size=64, fov=50.0))
    job.read()
    assert (job.focal_source, job.config.focal) == ("--fov", None)
    assert job.config.fov_deg == pytest.approx(50.0)        # a square photo: the same across either side
    job = FacePhotoJob(tmp_path / "exif.jpg", points, dict(size=64, fov=50.0, focal=700.0))
    job.read()
    assert (job.focal_source, job.config.focal, job.config.fov_deg) == ("--focal", 700.0, FaceFitConfig().fov_deg)
