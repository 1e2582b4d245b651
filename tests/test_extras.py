"""Optional libraries (papl_mapper.extras): a missing extra is a BackendUnavailableError naming it, the
command line says so in one line with a non-zero exit, and the core never needs an extra."""

from __future__ import annotations

import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from papl_mapper.errors import BackendUnavailableError, PaplError
from papl_mapper.extras import EXTRAS, require

from .conftest import make_map

ROOT = Path(__file__).resolve().parents[1]


def _absent(monkeypatch: pytest.MonkeyPatch, top: str) -> None:
    """Make `top` and its submodules unimportable, as if its extra were not installed."""
    for name in [n for n in sys.modules if n == top or n.startswith(top + ".")]:
        monkeypatch.setitem(sys.modules, name, None)
    monkeypatch.setitem(sys.modules, top, None)


def test_the_error_is_the_projects():
    assert issubclass(BackendUnavailableError, PaplError) and BackendUnavailableError.exit_code != 0


@pytest.mark.parametrize("top", sorted(EXTRAS))
def test_a_missing_library_names_its_extra(monkeypatch, top):
    extra, package = EXTRAS[top]
    _absent(monkeypatch, top)
    with pytest.raises(BackendUnavailableError, match=rf"{package}.*papl-mapper\[{extra}\]"):
        require(top, "this feature")


def test_every_extra_is_declared_in_pyproject():
    extras = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    for top, (extra, package) in EXTRAS.items():
        assert any(req.split(">")[0].split("=")[0] == package for req in extras[extra]), (top, extra)


def test_usd_and_dxf_exports_name_their_extra_on_the_command_line(monkeypatch, tmp_path, capsys):
    from papl_mapper.cli import main

    make_map().save(tmp_path / "m.papl")
    for top, suffix, extra in (("pxr", "usdc", "usd"), ("ezdxf", "dxf", "dxf")):
        with monkeypatch.context() as mp:
            _absent(mp, top)
            code = main(["export", str(tmp_path / "m.papl"), str(tmp_path / f"out.{suffix}")])
        err = capsys.readouterr().err.strip()
        assert code == BackendUnavailableError.exit_code
        assert len(err.splitlines()) == 1 and f"papl-mapper[{extra}]" in err, err
        assert not (tmp_path / f"out.{suffix}").exists()


def test_previews_report_viewer_and_ray_name_their_extra(monkeypatch, tmp_path):
    from papl_mapper.gui import plots
    from papl_mapper.gui.preview import render_views
    from papl_mapper.gui.viewer_window import import_window_libraries
    from papl_mapper.pipelines.batch_ray import import_ray

    m = make_map()
    with monkeypatch.context() as mp:
        _absent(mp, "pyvista")
        with pytest.raises(BackendUnavailableError, match=r"papl-mapper\[render\]"):
            render_views(m, tmp_path / "previews")
    with monkeypatch.context() as mp:
        _absent(mp, "matplotlib")
        with pytest.raises(BackendUnavailableError, match=r"papl-mapper\[render\]"):
            plots._figure()
    with monkeypatch.context() as mp:
        _absent(mp, "PySide6")
        with pytest.raises(BackendUnavailableError, match=r"papl-mapper\[viewer\]"):
            import_window_libraries()
    with monkeypatch.context() as mp:
        _absent(mp, "ray")
        with pytest.raises(BackendUnavailableError, match=r"papl-mapper\[ray\]"):
            import_ray()


def test_the_core_runs_without_any_extra(tmp_path):
    """Importing the pipeline, the CLI and the exporters, and writing the core formats, needs no extra."""
    blocked = sorted(EXTRAS)
    code = (
        "import sys\n"
        f"for name in {blocked!r}: sys.modules[name] = None\n"
        "import papl_mapper.cli, papl_mapper.pipelines.run, papl_mapper.pipelines.batch\n"
        "from papl_mapper.exporters import export\n"
        "from papl_mapper.map import Map\n"
        f"m = Map.load({str(tmp_path / 'm.papl')!r})\n"
        f"for s in ('ply', 'glb', 'gltf', 'obj', 'tubes.ply', 'tum', 'kitti', 'colmap'):\n"
        f"    export(m, {str(tmp_path)!r} + '/out.' + s)\n"
    )
    make_map().save(tmp_path / "m.papl")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-2000:]
    assert (tmp_path / "out.ply").is_file() and (tmp_path / "out.colmap").is_dir()


@pytest.mark.parametrize(
    "flags, top, extra",
    [
        (["--export", "ply,usdc"], "pxr", "usd"),
        (["--export", "plan.dxf"], "ezdxf", "dxf"),
        (["--render"], "pyvista", "render"),
        (["--report"], "matplotlib", "render"),
    ],
)
def test_run_refuses_a_missing_extra_before_any_work(monkeypatch, tmp_path, capsys, flags, top, extra):
    """`papl-map run` checks the libraries of the outputs it is asked for before the first frame: one
    line naming the extra, its exit code, and no frame read (no checkpoint, no log, no map)."""
    from papl_mapper.cli import main

    out = tmp_path / "out"
    _absent(monkeypatch, top)
    code = main(["run", str(ROOT / "samples" / "tiny" / "video.mp4"), "--out", str(out), *flags])
    err = capsys.readouterr().err.strip()
    assert code == BackendUnavailableError.exit_code
    assert len(err.splitlines()) == 1 and f"papl-mapper[{extra}]" in err, err
    assert not (out / ".checkpoint").exists() and not (out / "map.papl").exists()
