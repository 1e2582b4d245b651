"""Trajectory files have one home (papl_mapper.trajectory_io): its readers and writers, and that every
writer in the product goes through it with the one number format."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from papl_mapper.errors import InputError
from papl_mapper.exporters import ExportOptions
from papl_mapper.exporters.trajectory import export_kitti, export_tum
from papl_mapper.map import Camera, Keyframes, Map
from papl_mapper.trajectory_io import (
    TUM_HEADER,
    Trajectory,
    format_kitti,
    format_tum,
    read_tum,
    write_tum,
)


def _trajectory(n: int = 7, seed: int = 0) -> Trajectory:
    rng = np.random.default_rng(seed)
    T = np.repeat(np.eye(4)[None], n, axis=0)
    T[:, :3, :3] = Rotation.random(n, random_state=seed).as_matrix()
    T[:, :3, 3] = rng.normal(size=(n, 3)) * 10
    return Trajectory(np.arange(n) / 30.0, T, "t")


def test_tum_round_trip_is_exact(tmp_path: Path):
    traj = _trajectory()
    path = write_tum(tmp_path / "t.tum", traj)
    back = read_tum(path)
    assert np.array_equal(back.timestamps, traj.timestamps)
    assert np.array_equal(back.positions, traj.positions)
    assert np.allclose(back.T_wc, traj.T_wc, atol=1e-15)
    assert path.read_text().splitlines()[0] == TUM_HEADER


def test_tum_text_is_what_numpy_savetxt_wrote_before(tmp_path: Path):
    """The run's trajectory.tum keeps its bytes: `%.17g` rows as np.savetxt formats them."""
    traj = _trajectory()
    q = Rotation.from_matrix(traj.T_wc[:, :3, :3]).as_quat()
    with open(tmp_path / "ref.tum", "w") as fh:
        fh.write(TUM_HEADER + "\n")
        np.savetxt(fh, np.column_stack([traj.timestamps, traj.positions, q]), fmt="%.17g")
    assert format_tum(traj.timestamps, traj.T_wc) == (tmp_path / "ref.tum").read_text()


def test_kitti_rows_are_the_3x4_top():
    traj = _trajectory(3)
    rows = np.array([[float(v) for v in line.split()] for line in format_kitti(traj.T_wc).splitlines()])
    assert np.array_equal(rows.reshape(-1, 3, 4), traj.T_wc[:, :3, :4])


def test_exporters_use_the_same_text():
    traj = _trajectory(5)
    m = Map(Camera(640, 480, 500.0, 500.0, 319.5, 239.5))
    m.keyframes = Keyframes(np.arange(5), np.arange(5), traj.timestamps, traj.T_wc)
    tum = export_tum(m, ExportOptions()).decode()
    assert tum.splitlines()[0].startswith(TUM_HEADER)
    assert tum.splitlines()[1:] == format_tum(traj.timestamps, traj.T_wc).splitlines()[1:]
    assert export_kitti(m, ExportOptions()).decode() == format_kitti(traj.T_wc)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("0 1 2 3 0 0 0\n", "7 values"),
        ("0 1 2 3 0 0 0 x\n", "non-number"),
        ("0 1 2 3 0 0 0 0\n", "zero quaternion"),
        ("0 1 2 nan 0 0 0 1\n", "NaN"),
        ("0 1 2 3 0 0 0 1\n0 1 2 3 0 0 0 1\n", "share timestamp"),
        ("# only a comment\n", "no poses"),
    ],
)
def test_malformed_tum_names_file_and_problem(tmp_path: Path, text: str, message: str):
    path = tmp_path / "bad.tum"
    path.write_text(text)
    with pytest.raises(InputError, match=message):
        read_tum(path)


def test_product_writes_trajectories_only_through_trajectory_io():
    """No second TUM/KITTI writer: nothing outside trajectory_io formats quaternion rows itself."""
    root = Path(__file__).resolve().parents[1]
    offenders = []
    for folder in ("papl_mapper", "exporters", "gui", "pipelines"):
        for py in (root / folder).rglob("*.py"):
            if py.name == "trajectory_io.py":
                continue
            text = py.read_text()
            writes = "savetxt" in text or "def write_tum" in text or "as_quat()" in text
            if "qx qy qz qw" in text and writes:
                offenders.append(str(py.relative_to(root)))
    assert offenders == [], offenders
