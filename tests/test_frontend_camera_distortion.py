"""Camera files with distortion no lens has are refused before any frame is mapped."""

from __future__ import annotations

import json

import numpy as np
import pytest

from papl_mapper.cli import main
from papl_mapper.errors import InputError
from papl_mapper.frontend.camera import check_distortion
from papl_mapper.map import Camera


def _cam(dist):
    return Camera(640, 480, 500.0, 500.0, 319.5, 239.5, np.array(dist, float))


@pytest.mark.parametrize(
    "dist",
    [
        [0, 0, 0, 0, 0],
        [-0.28, 0.07, 0, 0, 0],
        [-0.4, 0.2, 0.001, -0.001, -0.05],
        [0.15, 0, 0, 0, 0],
        [0.5, 0, 0, 0, 0],
    ],
)
def test_lens_like_distortion_passes(dist):
    check_distortion(_cam(dist), "cam.json")


@pytest.mark.parametrize(
    ("dist", "what"),
    [
        ([1e6, 0, 0, 0, 0], "squeezing"),
        ([5.0, 0, 0, 0, 0], "squeezing"),
        ([-2.0, 0, 0, 0, 0], "folds"),
        ([0, -50.0, 0, 0, 0], "folds"),
    ],
)
def test_absurd_distortion_is_refused(dist, what):
    with pytest.raises(InputError, match=what):
        check_distortion(_cam(dist), "cam.json")


def test_run_refuses_it_in_one_line_before_mapping(tmp_path, capsys):
    import cv2

    rng = np.random.default_rng(0)
    frames = tmp_path / "frames"
    frames.mkdir()
    for i in range(3):
        cv2.imwrite(str(frames / f"{i:03d}.png"), rng.integers(0, 255, (48, 64), dtype=np.uint8))
    cam = tmp_path / "camera.json"
    cam.write_text(json.dumps({**_cam([1e6, 0, 0, 0, 0]).to_dict(), "width": 64, "height": 48}))
    assert main(["run", str(frames), "--camera", str(cam), "--out", str(tmp_path / "o")]) == 2
    errors = [line for line in capsys.readouterr().err.splitlines() if ": error: " in line]
    assert len(errors) == 1 and "implausible distortion" in errors[0] and str(cam) in errors[0]
    assert not (tmp_path / "o" / "map.papl").exists()
