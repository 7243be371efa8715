"""benchmarks/diagnose.py run --gt-poses: the map learned from true poses, the tracker's
decisions kept; what the mapper alone makes of a sequence."""

import pytest
import torch
from repo import benchmark

from dimslam.common.io.synth import write_sequence


@pytest.fixture
def diagnose(monkeypatch):
    return benchmark(monkeypatch, "diagnose")


def test_run_at_true_poses_puts_every_tracked_frame_on_its_ground_truth(
    diagnose, tmp_path, monkeypatch, capsys
):
    scene = tmp_path / "scene"
    write_sequence(scene, frames=18, width=160, height=120, seed=0)
    argv = ["diagnose.py", "run", str(scene), "--preset", "tiny", "--frames", "18"]
    monkeypatch.setattr("sys.argv", [*argv, "--gt-poses", "--depth-every", "4"])
    diagnose.main()
    lines = capsys.readouterr().out.splitlines()
    tracked = [ln for ln in lines if ln.startswith("frame ")]
    assert tracked, lines
    # The newest frame's error after the initialization's alignment: none at true poses.
    drifts = [float(ln.split("drift")[1].split("cm")[0]) for ln in tracked]
    assert max(drifts) < 0.01, tracked
    scaled = [ln for ln in tracked if "map scale" in ln]
    assert scaled, tracked
    # The tracker's pixels on the built-in scene at true poses: the scale it started with.
    textured = [float(ln.split("textured pixels")[1]) for ln in scaled]
    assert all(0.8 < s < 1.25 for s in textured), scaled
    # Each third of the view with its opacity; the last 10 frames' path at the true length.
    for ln in scaled:
        thirds = ln.split("thirds left/middle/right ")[1].split(" (")[0].split()
        assert len(thirds) == 3, ln
        for third in thirds:
            if third != "-":
                part_scale, opacity = map(float, third.split("@"))
                assert 0.5 < part_scale < 2 and 0 <= opacity <= 1, ln
        if "step " in ln:
            assert 0.9 < float(ln.split("step ")[1].split(",")[0]) < 1.1, ln


def test_basin_finds_the_warping_cost_lowest_near_the_true_depth(
    diagnose, tmp_path, monkeypatch, capsys
):
    scene = tmp_path / "scene"
    write_sequence(scene, frames=18, width=160, height=120, seed=0)
    argv = ["diagnose.py", "basin", str(scene), "--preset", "tiny", "--frames", "18"]
    monkeypatch.setattr("sys.argv", [*argv, "--rounds", "2", "--then", "mapper.grid_lr=2e-3"])
    diagnose.main()
    out = capsys.readouterr().out
    rows = [ln for ln in out.splitlines() if "cost at the true depth times" in ln]
    assert rows, out
    for row in rows:
        words = row.split()[6:]  # "x0.4 0.1338 x0.5 ..."
        costs = {float(x[1:]): float(c) for x, c in zip(words[::2], words[1::2], strict=True)}
        assert set(costs) == set(diagnose.BASIN_SCALES), row
        # Patches warped at their true depth from true poses match best (the scene is exact).
        assert 0.9 <= min(costs, key=costs.get) <= 1.1, row
    assert "mapping rounds of frames" in out and "after 2:" in out, out


def test_it_runs_on_the_threads_asked_and_refuses_none(diagnose, monkeypatch, capsys):
    """One thread by default, as benchmarks/table.py runs `dimslam run`, so that a whole run
    here is that run (threads change the sums' order, and a run's path with it)."""
    monkeypatch.setattr("sys.argv", ["diagnose.py", "run", "none", "--threads", "0"])
    with pytest.raises(SystemExit):
        diagnose.main()
    assert "--threads must be >= 1" in capsys.readouterr().err
    threads = torch.get_num_threads()
    try:
        called = []
        monkeypatch.setitem(diagnose.COMMANDS, "run", called.append)
        monkeypatch.setattr("sys.argv", ["diagnose.py", "run", "none"])
        diagnose.main()
        assert called and torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(threads)


def test_the_true_depth_at_the_true_poses_meshes_the_scene_to_a_centimetre(
    diagnose, tmp_path, monkeypatch, capsys
):
    """What the fusion and the protocol allow with nothing estimated: on the built-in scene
    (planar walls) the fused true depth lies on the true surface; what it misses of the
    culled ground truth is what no frame sees (the protocol has no occlusion test)."""
    scene, out = tmp_path / "scene", tmp_path / "out"
    write_sequence(scene, frames=12, width=160, height=120, seed=0)
    argv = ["diagnose.py", "mesh-truth", str(scene), "--preset", "tiny", "--frames", "12"]
    monkeypatch.setattr("sys.argv", [*argv, "--out", str(out)])
    diagnose.main()
    printed = capsys.readouterr().out
    assert "12 views" in printed, printed
    accuracy = float(printed.split("mesh accuracy")[1].split("cm")[0])
    assert accuracy < 2.0, printed
    assert (out / "mesh_truth.ply").stat().st_size > 0
    seen = float(printed.split("ground truth in the frustums:")[1].split("%")[0])
    assert 0 < seen < 100, printed

    def completion(part: str) -> float:
        return float(printed.split(part)[1].split()[0])

    # The split samples the surfaces as the protocol does: its whole is the protocol's figure.
    assert completion("over all of it") == float(printed.split("mesh completion")[1].split()[0])
    assert completion("the seen part") < 5.0 < completion("the hidden part"), printed

    # A run's mesh (here the truth's, at the true trajectory) split the same way.
    (out / "mesh_truth.ply").rename(out / "mesh.ply")
    monkeypatch.setattr("sys.argv", ["diagnose.py", "mesh-seen", *argv[2:], "--out", str(out)])
    diagnose.main()
    split = capsys.readouterr().out
    assert split.strip() == printed[printed.index("ground truth in the frustums") :].strip()


def test_the_mesh_split_into_the_views_scale_and_the_poses(diagnose, tmp_path, monkeypatch, capsys):
    """`mesh` prints each mesh view's depth (the map's and the plane sweep's) against the truth
    and evaluates the mapper's mesh, the map's depth alone, the same at the truth's scale per
    view, the true depth at the estimated poses, and the mesh after a longer refit; a refit
    of no iterations is refused before the run. (On 18 frames of a nearly straight walk the
    Sim(3) turns the meshes about the path, so their figures say little here: the test holds
    the depth's scale and the outputs.)"""
    scene, out = tmp_path / "scene", tmp_path / "out"
    write_sequence(scene, frames=18, width=160, height=120, seed=0)
    argv = ["diagnose.py", "mesh", str(scene), "--preset", "tiny", "--frames", "18"]
    monkeypatch.setattr("sys.argv", [*argv, "--out", str(out), "--refit", "0"])
    with pytest.raises(SystemExit, match="positive iteration counts"):
        diagnose.main()
    monkeypatch.setattr("sys.argv", [*argv, "--out", str(out), "--refit", "10"])
    diagnose.main()
    printed = capsys.readouterr().out
    rows = printed.split("(kept)\n")[1].split("mesh_map.ply")[0].splitlines()
    medians = [float(r.split("|")[1].split()[0]) for r in rows]
    swept = [float(r.split("|")[2].split()[0]) for r in rows if r.split("|")[2].strip() != "-"]
    # The tiny map's depth in map units is the truth's to a few percent on this scene, and
    # so is the plane sweep's where it found one (the views are the keyframes).
    assert len(rows) >= 2 and all(0.9 < m < 1.1 for m in medians), printed
    assert swept and all(0.9 < m < 1.1 for m in swept if m == m), printed
    names = [
        "mesh_map",
        "mesh_map_depth",
        "mesh_map_view_scale",
        "mesh_true_depth",
        "mesh_refit_10",
    ]
    for name in names:
        assert (out / f"{name}.ply").stat().st_size > 0
        section = printed.split(f"{name}.ply:")[1]
        assert float(section.split("mesh accuracy")[1].split("cm")[0]) >= 0, printed
