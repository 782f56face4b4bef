"""The report a user reads: the dense cloud's and the mesh's previews, depth maps on one colour scale with a colour
bar in the model's units, and the leave-one-out pose check of the last eval."""

from __future__ import annotations

from fullview.cli import main

DENSE = ["--set", "densify.working_width=512", "--set", "densify.rect_height=256", "--set",
         "densify.min_pair_inliers=30"]


def test_the_report_shows_previews_depth_scale_and_pose_check(tiny_dataset, tmp_path, tiny_set_args, capsys):
    ws = tmp_path / "ws"
    settings = [*tiny_set_args, *DENSE]
    assert main(["run", str(tiny_dataset), "-w", str(ws), *settings]) == 0
    assert main(["eval", str(tiny_dataset), "-w", str(ws), *settings]) == 0
    capsys.readouterr()
    assert main(["report", str(tiny_dataset), "-w", str(ws), *settings]) == 0
    page_path = capsys.readouterr().out.strip().splitlines()[-1]
    folder = ws / "tiny" / "report"
    page = (folder / "index.html").read_text()
    for name in ("dense_preview.png", "dense_mesh_preview.png", "depth_scale.png"):
        assert f"src='{name}'" in page and (folder / name).stat().st_size > 1000, name
    assert "distance (model units)" in page or "depth colour scale in model units" in page
    assert "<h2>Pose check</h2>" in page and "Flagged: none" in page
    assert page_path.endswith("index.html")
