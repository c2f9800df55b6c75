"""fit-face's focal length: --focal fixes it, else a photo's EXIF 35 mm equivalent focal length
starts it and centres its prior, else the typical 30 degree field of view does
(fitting.jobs.face_photo.with_exif_focal)."""
import math

import pytest

from softras_cl.fitting.jobs.face_photo import FacePhotoJob, exif_focal, with_exif_focal
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


def test_focal_given_beats_exif_beats_the_prior(tmp_path):
    with_exif, plain = _photos(tmp_path)
    config = FaceFitConfig()
    given = FaceFitConfig(focal=400.0)
    assert with_exif_focal(given, with_exif, (200, 300)) == (given, "--focal")      # --focal wins
    assert with_exif_focal(config, plain, (200, 300)) == (config, "prior")          # the 30 degrees
    exif_config, source = with_exif_focal(config, with_exif, (200, 300))
    assert source == "exif" and exif_config.focal is None
    assert exif_config.fov_deg == pytest.approx(exif_focal(with_exif, (200, 300))[1])
    # the fit starts at and centres its prior on that focal length (prepare_fit's fov_deg focal)
    start = 0.5 * 300 / math.tan(math.radians(exif_config.fov_deg) / 2)
    assert start == pytest.approx(exif_focal(with_exif, (200, 300))[0], rel=1e-9)


def test_a_face_job_reads_the_exif_focal(tmp_path, examples_data, examples_landmarks):
    """FacePhotoJob.read takes the EXIF focal length into its config (and says so) unless
    --focal is given; a photo without EXIF keeps the config's 30 degrees."""
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
