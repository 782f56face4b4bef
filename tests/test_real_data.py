"""Real Ricoh Theta S panoramas (../shared/datasets/openmvg-360): the sparse stages register every image."""

import json
from pathlib import Path

import pytest

from fullview.cli import main

SCHOOL = Path(__file__).resolve().parents[2] / "shared" / "datasets" / "openmvg-360" / "360_school"

pytestmark = pytest.mark.skipif(not SCHOOL.exists(), reason=f"real data not found at {SCHOOL} (../shared absent)")


def test_school_registers_all_four(tmp_path):
    # Half the default working width keeps this test to seconds; the benchmark runs the full setting.
    args = ["run", str(SCHOOL), "-w", str(tmp_path), "--until", "registration",
            "--set", "features.working_width=1024", "--set", "features.min_latitude_deg=-65",
            "--set", "filter.threshold_deg=0.7"]
    assert main(args) == 0
    summary = json.loads((tmp_path / "360_school" / "registration" / "manifest.json").read_text())["summary"]
    assert summary["registered"] == 4 and summary["unregistered"] == []
