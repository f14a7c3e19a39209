"""Meshcat replays (decoded and rendered in headless Chromium), live visualizer, plots."""

import base64
import os
import re
import subprocess

import matplotlib.pyplot as plt
import numpy as np
import pytest

from hybridctl import systems, viz

ALL = systems.known_systems()
CHROMIUM = os.environ.get("HYBRIDCTL_CHROMIUM", "/usr/bin/chromium")
# WebGL through SwiftShader (software): works with or without a GPU.
CHROMIUM_FLAGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
    "--disable-quic", "--no-first-run", "--disable-background-networking", "--disable-component-update",
    "--disable-sync", "--window-size=800,600", "--virtual-time-budget=3000",
]


@pytest.fixture(scope="module")
def meshcat():
    """One localhost server for the module (each replay replaces the last)."""
    return viz.start_meshcat()


def swing(system, duration=2.0, rate=100.0):
    """times, states of a made-up motion about the hanging pose that moves every coordinate."""
    times = np.arange(0.0, duration, 1.0 / rate)
    states = np.tile(system.initial_state.nominal, (len(times), 1))
    n_q = system.n_states // 2
    for i in range(n_q):
        states[:, i] += 0.5 * np.sin(2 * np.pi * times / duration + i)
    return times, states


def messages(html):
    """The meshcat commands embedded in a StaticHtml page (base64 msgpack), decoded."""
    umsgpack = pytest.importorskip("umsgpack")
    blobs = re.findall(r"data:application/octet-binary;base64,([A-Za-z0-9+/=]+)", html)
    return [umsgpack.unpackb(base64.b64decode(blob)) for blob in blobs]


def animation_tracks(html):
    """{(path, track name): [values per frame]} of the page's animation."""
    animations = [m for m in messages(html) if m.get("type") == "set_animation"]
    assert len(animations) == 1, "the page holds no (or several) recorded animations"
    return {(a["path"], t["name"]): [k["value"] for k in t["keys"]]
            for a in animations[0]["animations"] for t in a["clip"]["tracks"]}


def test_start_meshcat_binds_localhost(meshcat):
    assert meshcat.web_url().startswith("http://localhost:")


@pytest.mark.parametrize("name", ALL)
def test_replay_html_records_the_animation(name, meshcat, tmp_path):
    system = systems.load(name)
    times, states = swing(system)
    path = tmp_path / f"{name}.html"
    html = viz.replay_html(system, times, states, path=path, meshcat=meshcat, fps=50)
    assert html and path.read_text() == html
    tracks = animation_tracks(html)
    assert all(p.startswith("/drake/replay/") for p, _ in tracks)
    n_frames = 100  # 1.99 s at 50 fps, frames 0 .. 99
    assert {len(v) for v in tracks.values()} == {n_frames}
    moving = [key for key, v in tracks.items() if not np.allclose(v[0], v[n_frames // 4], atol=1e-3)]
    assert moving, "no body moves in the recorded animation"
    # The camera is a 2D (orthographic) side view.
    cameras = [m for m in messages(html) if m.get("type") == "set_object" and "Cameras" in m["path"]]
    assert cameras and cameras[-1]["object"]["object"]["type"] == "OrthographicCamera"


def test_replay_html_default_server_and_torch_states():
    torch = pytest.importorskip("torch")
    system = systems.load("pendulum")
    times, states = swing(system, duration=0.5)
    html = viz.replay_html(system, torch.as_tensor(times), torch.as_tensor(states))
    assert len(animation_tracks(html)[("/drake/replay/arm", ".quaternion")]) == 25


def test_an_echoed_replay_page_is_one_line_and_replays_reuse_one_server(tmp_path):
    """Echoing ``viz.replay_html(...)`` in a notebook shows the replay (``_repr_html_``), and its repr is one
    line instead of megabytes of HTML; calls without ``meshcat`` share one server instead of starting one each."""
    system = systems.load("pendulum")
    times, states = swing(system, duration=0.5)
    first = viz.replay_html(system, times, states, path=tmp_path / "a.html")
    server = viz.shared_meshcat()
    second = viz.replay_html(system, times, states)
    assert viz.shared_meshcat() is server
    assert isinstance(first, str) and len(first) > 10_000 and (tmp_path / "a.html").read_text() == first
    assert "\n" not in repr(first) and len(repr(first)) < 200 and str(tmp_path / "a.html") in repr(first)
    assert repr(second).startswith("<meshcat replay page:") and "written" not in repr(second)
    assert second._repr_html_().startswith("<iframe srcdoc=") and "&lt;" in second._repr_html_()


def test_replay_html_rejects_bad_input(meshcat):
    system = systems.load("acrobot")
    times, states = swing(system, duration=0.2)
    with pytest.raises(ValueError, match="times and states"):
        viz.replay_html(system, times[:-1], states, meshcat=meshcat)
    with pytest.raises(ValueError, match=r"states must have shape \(T, 4\)"):
        viz.replay_html(system, times, states[:, :3], meshcat=meshcat)
    bad = states.copy()
    bad[3, 1] = np.nan
    with pytest.raises(ValueError, match="states contains NaN"):
        viz.replay_html(system, times, bad, meshcat=meshcat)
    with pytest.raises(ValueError, match="times must be strictly increasing"):
        viz.replay_html(system, times[::-1], states, meshcat=meshcat)
    with pytest.raises(ValueError, match="fps"):
        viz.replay_html(system, times, states, meshcat=meshcat, fps=0)


def test_add_meshcat_shows_a_simulated_diagram(meshcat):
    from pydrake.systems.analysis import Simulator
    from pydrake.systems.framework import DiagramBuilder
    from hybridctl.systems.plants import add_plant

    system = systems.load("cartpole")
    builder = DiagramBuilder()
    handle, scene_graph = add_plant(system, builder, with_geometry=True)
    visualizer = viz.add_meshcat(builder, scene_graph, meshcat)
    diagram = builder.Build()
    simulator = Simulator(diagram)
    context = handle.plant.GetMyMutableContextFromRoot(simulator.get_mutable_context())
    handle.actuation_input.FixValue(context, np.zeros(1))
    simulator.AdvanceTo(0.05)
    assert visualizer.get_name()
    assert meshcat.HasPath("/drake/visualizer/cartpole/pole1")
    with pytest.raises(ValueError, match="scene_graph"):
        viz.add_meshcat(builder, None, meshcat)


def screenshot(html_path, png_path, tmp_path):
    profile = tmp_path / f"profile-{png_path.stem}"
    cmd = [CHROMIUM, *CHROMIUM_FLAGS, f"--user-data-dir={profile}", f"--screenshot={png_path}",
           html_path.as_uri()]
    result = subprocess.run(cmd, capture_output=True, text=True, timeout=90)
    assert png_path.exists(), f"chromium wrote no screenshot (rc {result.returncode}):\n{result.stderr[-2000:]}"
    from PIL import Image
    return np.asarray(Image.open(png_path).convert("RGB")).astype(int)


# CI sets HYBRIDCTL_REQUIRE_CHROMIUM=1 (after installing it), so the render test cannot silently skip there.
@pytest.mark.skipif(not os.path.exists(CHROMIUM) and not os.environ.get("HYBRIDCTL_REQUIRE_CHROMIUM"),
                    reason=f"{CHROMIUM} not installed (apt package chromium)")
def test_acrobot_replay_renders_in_chromium(tmp_path):
    """Render the page in headless Chromium; the robot must be drawn, in our angle convention."""
    meshcat = viz.start_meshcat()  # a fresh scene: nothing from other tests in the picture
    system = systems.load("acrobot")
    times = np.arange(0.0, 0.5, 0.01)
    states = np.tile([0.3, 0.5, 0.0, 0.0], (len(times), 1))  # th1 0.3 rad above horizontal, elbow +0.5
    robot_html = tmp_path / "robot.html"
    viz.replay_html(system, times, states, path=robot_html, meshcat=meshcat)
    meshcat.Delete("replay")  # the same page (camera, background) without the robot
    empty_html = tmp_path / "empty.html"
    empty_html.write_text(meshcat.StaticHtml())

    robot = screenshot(robot_html, tmp_path / "robot.png", tmp_path)
    empty = screenshot(empty_html, tmp_path / "empty.png", tmp_path)
    assert robot.shape == empty.shape == (600, 800, 3)
    assert len(np.unique(robot.reshape(-1, 3), axis=0)) > 300, "the page looks blank"
    drawn = np.abs(robot - empty).max(axis=-1) > 60
    assert drawn.sum() > 1500, f"only {drawn.sum()} pixels differ from the empty scene"
    r, g, b = robot[..., 0], robot[..., 1], robot[..., 2]
    red = (r > 120) & (g < 80) & (b < 80)     # upper link, Drake's AcrobotGeometry colour (1, 0, 0)
    blue = (b > 120) & (r < 80) & (g < 80)    # lower link (0, 0, 1)
    assert red.sum() > 300 and blue.sum() > 300, (red.sum(), blue.sum())
    e = empty
    assert not ((e[..., 0] > 120) & (e[..., 1] < 80) & (e[..., 2] < 80)).any(), "red without the robot"
    # The base (world origin) is at the image centre, +x to the right, +z up: the
    # upper link points right and a little up, the lower link further up.
    red_y, red_x = np.argwhere(red).mean(axis=0)
    blue_y, blue_x = np.argwhere(blue).mean(axis=0)
    assert red_x > 400 + 30 and red_y < 300, (red_x, red_y)
    assert blue_x > red_x and blue_y < red_y - 30, (blue_x, blue_y)


@pytest.mark.parametrize("name", ["acrobot", "double_cartpole"])
def test_plot_trajectory(name, tmp_path):
    system = systems.load(name)
    times, states = swing(system)
    inputs = system.action_limit * np.sin(3 * times)
    gate = (times > 1.0).astype(int)
    path = tmp_path / "sub" / "trajectory.png"
    fig = viz.plot_trajectory(times, states, inputs, gate, system, path=path, title="test")
    try:
        assert path.stat().st_size > 10_000
        assert len(fig.axes) == system.n_states + 2
        labels = [ax.get_ylabel() for ax in fig.axes]
        assert labels[system.angle_indices[0]].endswith("[rad]")
        limit_lines = [ln for ln in fig.axes[system.n_states].get_lines() if ln.get_linestyle() == "--"]
        assert sorted(ln.get_ydata()[0] for ln in limit_lines) == [-system.action_limit, system.action_limit]
        # the input panel has its unit (every shipped spec gives one) and the limit lines a legend entry
        assert system.action_unit in ("N", "N m") and labels[system.n_states].endswith(f"[{system.action_unit}]")
        legend = [t.get_text() for t in fig.axes[system.n_states].get_legend().get_texts()]
        assert f"limit +-{system.action_limit:g} {system.action_unit}" in legend
        assert all(label.endswith(("[rad]", "[rad/s]", "[m]", "[m/s]")) for label in labels[:system.n_states])
    finally:
        plt.close(fig)
    with pytest.raises(ValueError, match="gate"):
        viz.plot_trajectory(times, states, inputs, gate + 1, system)
    with pytest.raises(ValueError, match="states"):
        viz.plot_trajectory(times, states[1:], inputs, gate, system)


def test_plot_balance_map(tmp_path):
    th = np.linspace(-np.pi, np.pi, 11)
    balanced = np.add.outer(np.cos(th), np.cos(th)) > 0.5
    path = tmp_path / "map.png"
    fig = viz.plot_balance_map(th, th[:-1], balanced[:, :-1], path=path, title="acrobot")
    try:
        assert path.stat().st_size > 5_000
        assert len(fig.axes) == 1
        fraction = balanced[:, :-1].mean()
        assert f"{100 * fraction:.1f}% balanced" in fig.axes[0].get_title()
    finally:
        plt.close(fig)
    with pytest.raises(ValueError, match="balanced must have shape"):
        viz.plot_balance_map(th, th, balanced[:, :-1])
    with pytest.raises(ValueError, match="th1_values must be strictly increasing"):
        viz.plot_balance_map(th[::-1], th, balanced)


def test_plot_trajectory_wraps_angles_about_the_goal():
    """An acrobot run whose elbow spins two full turns is drawn within goal +- pi, not at 4 pi."""
    system = systems.load("acrobot")
    times = np.arange(0.0, 4.0, 0.01)
    states = np.tile(system.goal, (len(times), 1)).astype(float)
    states[:, 0] += 0.2 * np.sin(times)                     # th1 near the goal
    states[:, 1] = 4 * np.pi * np.clip(times / 3.0, 0, 1)   # th2: 0 -> 4 pi, then rests there
    inputs, gate = np.zeros(len(times)), (times > 3.0).astype(int)
    fig = viz.plot_trajectory(times, states, inputs, gate, system)
    try:
        for i in system.angle_indices:
            goal = system.goal[i]
            y = np.concatenate([ln.get_ydata() for ln in fig.axes[i].get_lines() if ln.get_linestyle() == "-"])
            y = y[np.isfinite(y)]
            assert y.size >= len(times)
            assert np.all(y >= goal - np.pi - 1e-9) and np.all(y < goal + np.pi + 1e-9), (i, y.min(), y.max())
        th2 = [ln for ln in fig.axes[1].get_lines() if ln.get_linestyle() == "-"][0].get_ydata()
        assert abs(th2[-1] - system.goal[1]) < 1e-9, "4 pi is drawn at the goal"
        assert np.isnan(th2).sum() == 2, "the line breaks where it wraps (through pi and 3 pi)"
        rates = fig.axes[system.n_states // 2].get_lines()[0].get_ydata()   # rates are not wrapped
        np.testing.assert_array_equal(rates, states[:, system.n_states // 2])
    finally:
        plt.close(fig)
    from hybridctl.viz.plots import wrap_about_goal
    wrapped = wrap_about_goal(states, system)
    np.testing.assert_allclose(wrapped[:, [0, 2, 3]], states[:, [0, 2, 3]], atol=1e-12)   # already near the goal
    np.testing.assert_allclose(wrapped[-1, 1], system.goal[1], atol=1e-9)


def legend_labels(fig):
    legends = [ax.get_legend() for ax in fig.axes if ax.get_legend() is not None] + fig.legends
    assert legends, "the figure has no legend"
    return [text.get_text() for legend in legends for text in legend.get_texts()]


def test_plot_balance_map_has_a_legend():
    th = np.linspace(-np.pi, np.pi, 9)
    balanced = np.add.outer(np.cos(th), np.cos(th)) > 0.5
    fig = viz.plot_balance_map(th, th, balanced)
    try:
        assert legend_labels(fig) == ["balanced", "not balanced"]
    finally:
        plt.close(fig)
    diverged = np.zeros_like(balanced)
    diverged[0, 0] = True                                    # a corner run that diverged
    assert not balanced[0, 0]
    fig = viz.plot_balance_map(th, th, balanced, diverged=diverged)
    try:
        assert legend_labels(fig) == ["balanced", "not balanced", "diverged"]
        mesh = fig.axes[0].collections[0]
        colours = mesh.cmap(mesh.norm(mesh.get_array().reshape(9, 9)))   # [th2, th1]
        from matplotlib.colors import to_rgba
        assert np.allclose(colours[0, 0], to_rgba("tab:orange"))
        assert np.allclose(colours[4, 4], to_rgba("black"))              # the centre balanced
    finally:
        plt.close(fig)
    fig = viz.plot_balance_map(th, th, balanced, diverged=np.zeros_like(balanced))
    try:
        assert legend_labels(fig) == ["balanced", "not balanced"], "no diverged entry when none diverged"
    finally:
        plt.close(fig)
    with pytest.raises(ValueError, match="diverged must have the shape"):
        viz.plot_balance_map(th, th, balanced, diverged=diverged[:, :-1])
