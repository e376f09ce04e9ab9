"""The README's worked example, verbatim, on the bundled Pose2Sim trial (assets/pose2sim_trial)."""
import json
from pathlib import Path

import numpy as np
import pytest

from dloe_sfm import cli

REPO = Path(__file__).resolve().parents[1]

# the README's commands, as typed from the repository's root (``dloe-sfm`` = ``cli.main``)
IMPORT = ("import-calibration assets/pose2sim_trial/calibration/Calib.qca.txt --format qualisys "
          "--keypoints assets/pose2sim_trial/pose --out ws/sparse/0")
RECONSTRUCT = ("reconstruct ws --keypoints assets/pose2sim_trial/pose --format openpose --fps 60 "
               "--out out")


def readme_commands() -> list[str]:
    """The ``dloe-sfm ...`` lines of the README's worked example."""
    text = (REPO / "README.md").read_text(encoding="utf-8")
    section = text.split("## Worked example", 1)[1].split("\n## ", 1)[0]
    return [line.removeprefix("dloe-sfm ").strip() for line in section.splitlines()
            if line.startswith("dloe-sfm ")]


def test_readme_shows_these_commands() -> None:
    assert readme_commands() == [IMPORT, RECONSTRUCT]


@pytest.mark.slow
def test_worked_example_runs_and_its_trc_reads_back(tmp_path, monkeypatch) -> None:
    (tmp_path / "assets").symlink_to(REPO / "assets")
    monkeypatch.chdir(tmp_path)
    assert cli.main(IMPORT.split()) == 0
    assert cli.main(RECONSTRUCT.split()) == 0
    out = tmp_path / "out"
    for name in ("trajectories.trc", "trajectories.c3d", "trajectories_wide.csv", "sequence.csv",
                 "report.json", "plots/animation.gif"):
        assert (out / name).is_file(), name
    report = json.loads((out / "report.json").read_text())
    assert (report["images"], report["subjects"], report["events"]) == (100, 1, 1)
    assert report["layout"] == "BODY_25B"
    assert report["time_unit"] == "s"
    # the README's snippet
    header = (out / "trajectories.trc").read_text().splitlines()[:5]
    rate, camera_rate, frames, markers, units = header[2].split("\t")[:5]
    assert (float(rate), float(camera_rate), int(markers), units) == (60.0, 60.0, 25, "mm")
    data = np.genfromtxt(out / "trajectories.trc", delimiter="\t", skip_header=5)
    assert data.shape == (int(frames), 2 + 3 * 25)
    assert np.allclose(np.diff(data[:, 1]), 1 / 60)  # Time in seconds
    assert header[3].split()[2:4] == ["Nose", "LEye"]
    # issue 39: at most 20 % of the rows empty (the gaps are counted in image periods)
    assert np.isfinite(data[:, 2:]).any(axis=1).sum() >= 0.8 * int(frames)
