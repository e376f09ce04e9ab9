"""The animation of a result (plots/animation.gif), `dloe-sfm view`, and the plot fixes
(every point in trajectories.png, ticks on the events plot of one event)."""

from __future__ import annotations

import ctypes.util
import shutil
import subprocess
import sys
import types
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sp
from PIL import Image, ImageSequence
from scenes import look_at

from dloe_sfm import Capture, Result, cli, viz
from dloe_sfm.core.capture import project
from dloe_sfm.export import export_outputs
from dloe_sfm.keypoints import Layout

N, STREAMS, P = 18, 3, 5
LAYOUT = Layout("toy", ["head", "neck", "hip", "knee", "foot"], [(0, 1), (1, 2), (2, 3), (3, 4)])


def toy(n: int = N, subjects: int = 1, events: int = 1) -> tuple[Capture, Result]:
    """A figure of P points walking a circle, seen by 3 cameras; estimated order reversed."""
    rng = np.random.default_rng(0)
    t = np.linspace(0.0, 1.0, n)
    stream = np.arange(n) % STREAMS
    offsets = np.array([[0, 0, 1.7], [0, 0, 1.5], [0, 0, 1.0], [0.1, 0, 0.5], [0.1, 0, 0.05]])
    centre = np.stack([np.cos(2 * np.pi * t), np.sin(2 * np.pi * t), 0 * t], axis=1)
    X = np.concatenate([centre[:, None, :] + offsets[None] + [1.5 * s, 0, 0]
                        for s in range(subjects)], axis=1)
    angle = 2 * np.pi * stream / STREAMS
    C = np.stack([5 * np.cos(angle), 5 * np.sin(angle), np.full(n, 1.0)], axis=1)
    R = np.stack([look_at(c, np.array([0.0, 0.0, 1.0])) for c in C])
    K = np.tile(np.array([[800.0, 0, 320], [0, 800, 240], [0, 0, 1]]), (n, 1, 1))
    x = project(X, K, R, C)
    x[4, 2] = np.nan
    capture = Capture(x=x, K=K, R=R, C=C, stream=stream, frame=np.arange(n) // STREAMS,
                      image_names=np.array([f"cam{s}/{k:04d}.jpg" for k, s in enumerate(stream)]))
    chain = sp.diags(np.ones(n - 1), 1, shape=(n, n), format="csr")
    ids = {} if subjects == 1 else {"subject_id": np.repeat(np.arange(subjects), P),
                                     "point_id": np.tile(np.arange(P), subjects)}
    result = Result(
        X=X + 1e-3 * rng.normal(size=X.shape), order=np.arange(n)[::-1].copy(), A=chain,
        W=chain, D=np.ones(n), events=np.arange(n) * events // n, embedding=t,
        cost_history=np.array([1.0]), change_history=np.array([0.1]), nit=1, success=True,
        message="converged", seconds=0.1, **ids)
    return capture, result


def static_points() -> tuple[np.ndarray, np.ndarray]:
    """A floor grid around the scene and far-away points the animation must crop away."""
    g = np.linspace(-2.0, 2.0, 21)
    floor = np.stack(np.meshgrid(g, g, [0.0]), axis=-1).reshape(-1, 3)
    far = np.array([[50.0, 0, 0], [0, -80.0, 3]])
    xyz = np.concatenate([floor, far])
    return xyz, np.tile(np.array([[90, 120, 60]], dtype=np.uint8), (len(xyz), 1))


@pytest.fixture(scope="module")
def out(tmp_path_factory) -> Path:
    """A reconstruct output folder (plots included) of the toy capture."""
    capture, result = toy()
    xyz, rgb = static_points()
    workspace = types.SimpleNamespace(static_xyz=xyz, static_rgb=rgb, image_dir=None,
                                      model_dir=None)
    folder = tmp_path_factory.mktemp("view") / "out"
    export_outputs(folder, capture, result, workspace=workspace, layout=LAYOUT)
    return folder


def gif_frames(path: Path) -> list[np.ndarray]:
    with Image.open(path) as im:
        return [np.asarray(frame.convert("RGB")) for frame in ImageSequence.Iterator(im)]


def test_reconstruct_output_has_a_readable_animation(out) -> None:
    gif = out / "plots" / "animation.gif"
    with Image.open(gif) as im:
        assert im.format == "GIF" and im.size == (640, 560) and im.n_frames == N
    frames = gif_frames(gif)
    assert all((a != b).any() for a, b in zip(frames, frames[1:], strict=False))
    assert gif.stat().st_size < 1_000_000


def test_animation_caps_frames_and_draws_every_subject(tmp_path) -> None:
    capture, result = toy(n=40, subjects=2, events=2)
    edges = np.array([[0, 1], [1, 2], [5, 6], [6, 7]])
    colors = np.tile(np.array([[230, 30, 30], [30, 30, 230]], dtype=np.uint8), (5, 1))
    xyz, rgb = static_points()
    path = viz.animate(result.X, result.order, tmp_path / "a.gif", image_names=capture.image_names,
                       events=result.events, edges=edges, colors=colors,
                       subject_id=result.subject_id, observed=capture.visible, static_xyz=xyz,
                       static_rgb=rgb, max_frames=10, width_px=320)
    frames = gif_frames(path)
    assert len(frames) == 10 and frames[0].shape == (280, 320, 3)
    assert all((a != b).any() for a, b in zip(frames, frames[1:], strict=False))
    # the points' exact colours survive the GIF palette
    for colour in colors[:2]:
        assert (frames[0] == colour).all(axis=2).sum() > 10
    assert list(viz.animation_frames(40, 10)) == [0, 4, 9, 13, 17, 22, 26, 30, 35, 39]


def test_static_points_are_cropped_to_the_scene() -> None:
    _, result = toy()
    centre, half = viz.scene_box(result.X)
    xyz, rgb = static_points()
    kept, kept_rgb = viz.crop_static(xyz, rgb, centre, half, max_points=50)
    assert len(kept) == 50 and len(kept_rgb) == 50
    assert (np.abs(kept - centre) <= half).all()
    assert np.abs(xyz - centre).max() > 10 * half  # the far points existed and were dropped


def test_trajectories_draw_every_point_or_say_how_many() -> None:
    X = np.random.default_rng(1).normal(size=(30, 8, 3)).cumsum(axis=0)
    names = [f"p{k}" for k in range(8)]
    fig = viz.trajectories_figure(X, np.arange(30), point_names=names)
    ax = fig.axes[0]
    assert [t.get_text() for t in ax.get_legend().get_texts()] == names
    assert "all 8 points" in ax.get_title()
    fig = viz.trajectories_figure(np.concatenate([X] * 3, axis=1), np.arange(30), max_points=6)
    ax = fig.axes[0]
    assert len(ax.get_legend().get_texts()) == 6 and "6 of 24 points" in ax.get_title()


def test_events_plot_of_one_event_has_ticks() -> None:
    for events in (1, 3):
        _, result = toy(n=30, events=events)
        fig = viz.events_figure(result)
        ax = fig.axes[0]
        labels = [t.get_text() for t in ax.get_xticklabels()]
        assert len(ax.get_xticks()) == 3 * events and labels[:3] == ["\u22121", "0", "1"]
        left, right = ax.get_xlim()
        assert left < min(ax.get_xticks()) and max(ax.get_xticks()) < right
        top = [t.get_text() for c in ax.child_axes for t in c.get_xticklabels()]
        assert top == [f"event {e}" for e in range(events)]


def run_cli(args: list[str], capsys) -> tuple[int, str]:
    with pytest.raises(SystemExit) as exc:
        cli.main(args)
    return exc.value.code, capsys.readouterr().err


def test_view_without_a_display_points_to_the_gif(out, monkeypatch, capsys) -> None:
    monkeypatch.setattr(sys, "platform", "linux")
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    code, err = run_cli(["view", str(out)], capsys)
    assert code == 2
    assert err == (f"dloe-sfm: error: no display to open a window on; the animation is in "
                   f"{out / 'plots' / 'animation.gif'}\n")


@pytest.mark.skipif(ctypes.util.find_library("X11") is None, reason="needs libX11")
def test_view_with_an_unreachable_x_display(out, monkeypatch, capsys) -> None:
    monkeypatch.setattr(sys, "platform", "linux")
    monkeypatch.setenv("DISPLAY", ":987")  # no X server there: open3d would go offscreen
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    code, err = run_cli(["view", str(out)], capsys)
    assert code == 2 and err.count("\n") == 1
    assert err.startswith("dloe-sfm: error: cannot connect to the X display :987; the animation")


def test_view_of_a_missing_or_foreign_folder(tmp_path, capsys) -> None:
    code, err = run_cli(["view", str(tmp_path / "nowhere")], capsys)
    assert code == 2 and err.count("\n") == 1 and str(tmp_path / "nowhere") in err
    code, err = run_cli(["view", str(tmp_path)], capsys)
    assert code == 2 and err.count("\n") == 1
    assert f"{tmp_path}: no trajectories.npz" in err


def test_view_save_gif(out, tmp_path, capsys) -> None:
    gif = tmp_path / "v.gif"
    assert cli.main(["view", str(out), "--save-gif", str(gif), "--fps", "5"]) == 0
    with Image.open(gif) as im:
        assert im.n_frames == N and im.info["duration"] == 200
    code, err = run_cli(["view", str(out), "--save-gif", str(gif)], capsys)
    assert code == 2 and f"{gif}: output file exists (use --overwrite" in err
    notes = tmp_path / "notes.gif"
    notes.write_text("not a picture")
    for overwrite in ([], ["--overwrite"]):
        code, err = run_cli(["view", str(out), "--save-gif", str(notes), *overwrite], capsys)
        assert code == 2 and f"{notes}: exists and is not a .gif image, never replaced; " \
            "choose another --save-gif file" in err, err
    assert notes.read_text() == "not a picture"
    code, err = run_cli(["view", str(out), "--save-gif", str(tmp_path / "v.mp4")], capsys)
    assert code == 2 and ".gif" in err


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("xvfb-run") is None, reason="needs xvfb-run (apt: xvfb)")
def test_view_plays_in_a_window_under_xvfb(out, tmp_path) -> None:
    shot = tmp_path / "shot.png"
    run = subprocess.run(["xvfb-run", "-a", "-s", "-screen 0 1280x1024x24", sys.executable, "-m",
                          "dloe_sfm.stages.view", str(out), "--frames", "3", "--fps", "30",
                          "--screenshot", str(shot)],
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    image = np.asarray(Image.open(shot).convert("RGB")).astype(int)
    saturated = (image.max(axis=2) - image.min(axis=2)) > 80  # the points' colours
    assert image.shape == (768, 1024, 3) and saturated.sum() > 100
