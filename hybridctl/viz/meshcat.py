"""Meshcat viewing: a localhost server, a visualizer for diagrams, and HTML replays.

Live viewing of a simulated diagram::

    meshcat = start_meshcat()
    handle, scene_graph = hybridctl.systems.plants.add_plant(system, builder, with_geometry=True)
    add_meshcat(builder, scene_graph, meshcat)
    print("open", meshcat.web_url())              # http://localhost:7000 by default

Offline replay of a trajectory (simulation or torch rollout)::

    html = replay_html(system, times, states, path="replay.html")

Meshcat must be used from the thread that created it (Drake raises SystemExit
otherwise, which ``except Exception`` does not catch).

A replay page embeds the bytes of every mesh the model draws. A multibody model's plant is built
only through ``systems.symbolic.parse_plant``, which checks every file the model names first
(``systems.model_files``: regular files of bounded size in the model's folder or ``package://drake/``),
so no other local file reaches a page, and no device or FIFO is opened.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from pydrake.geometry import Meshcat, MeshcatParams, MeshcatVisualizer, MeshcatVisualizerParams
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.systems.framework import DiagramBuilder

if TYPE_CHECKING:
    from hybridctl.systems import System

__all__ = ["start_meshcat", "add_meshcat", "replay_html"]

# Replay frame rate: enough for smooth motion, few enough frames for a small HTML file.
DEFAULT_FPS = 50.0
# Extra room (m) around the robot's reach in the 2D view.
_VIEW_MARGIN = 0.3


def start_meshcat(port: int | None = None, host: str = "localhost") -> Meshcat:
    """Start a Meshcat server bound to ``host`` (localhost by default).

    ``port`` None picks the first free port from 7000 up. Open ``meshcat.web_url()``
    in a browser to view it. Use the returned object only from the calling thread.
    """
    if port is not None and not 1 <= int(port) <= 65535:
        raise ValueError(f"port must be in [1, 65535] or None, got {port}")
    params = MeshcatParams()
    params.host = host
    if port is not None:
        params.port = int(port)
    return Meshcat(params)


def add_meshcat(builder: DiagramBuilder, scene_graph, meshcat: Meshcat,
                publish_period: float | None = None) -> MeshcatVisualizer:
    """Add a MeshcatVisualizer of ``scene_graph`` to ``builder``; returns the visualizer.

    A thin wrapper of ``MeshcatVisualizer.AddToBuilder``: simulating the built
    diagram then shows the robot live at ``meshcat.web_url()``. ``publish_period``
    (s, > 0) defaults to Drake's 1/64 s.
    """
    if scene_graph is None:
        raise ValueError("scene_graph is None: add the plant with add_plant(..., with_geometry=True)")
    params = MeshcatVisualizerParams()
    if publish_period is not None:
        if not publish_period > 0:
            raise ValueError(f"publish_period must be > 0 s, got {publish_period}")
        params.publish_period = float(publish_period)
    return MeshcatVisualizer.AddToBuilder(builder, scene_graph, meshcat, params)


def _as_numpy(value) -> np.ndarray:
    if hasattr(value, "detach"):  # torch tensor
        value = value.detach().cpu().numpy()
    return np.asarray(value, dtype=float)


def _check_trajectory(system: "System", times, states) -> tuple[np.ndarray, np.ndarray]:
    times, states = _as_numpy(times), _as_numpy(states)
    if times.ndim != 1 or times.size < 1:
        raise ValueError(f"times must have shape (T,) with T >= 1, got {times.shape}")
    if states.ndim != 2 or states.shape[1] != system.n_states:
        raise ValueError(f"states must have shape (T, {system.n_states}) for {system.name}, got {states.shape}")
    if states.shape[0] != times.shape[0]:
        raise ValueError(f"times and states lengths differ: {times.shape[0]} vs {states.shape[0]}")
    if not np.isfinite(times).all():
        raise ValueError("times contains NaN or Inf")
    if not np.isfinite(states).all():
        raise ValueError("states contains NaN or Inf")
    if np.any(np.diff(times) <= 0):
        raise ValueError("times must be strictly increasing")
    return times, states


class _Scene:
    """A visual-only diagram: the system's geometry posed from a state we set per frame."""

    def __init__(self, system: "System", meshcat: Meshcat, fps: float):
        from hybridctl.systems import plants

        self.system = system
        builder = DiagramBuilder()
        # The plant only holds the state we set per frame; it is never simulated.
        handle, scene_graph = plants.add_plant(system, builder, with_geometry=True)
        self.plant = handle.plant
        params = MeshcatVisualizerParams()
        params.publish_period = 1.0 / fps
        params.prefix = "replay"
        self.visualizer = MeshcatVisualizer.AddToBuilder(builder, scene_graph, meshcat, params)
        self.diagram = builder.Build()
        self.context = self.diagram.CreateDefaultContext()
        self.plant_context = self.plant.GetMyMutableContextFromRoot(self.context)
        self.visualizer_context = self.visualizer.GetMyContextFromRoot(self.context)

    def publish(self, t: float, x: np.ndarray) -> None:
        """Pose the geometry at state ``x`` (our convention) and publish it at time ``t``."""
        self.context.SetTime(t)
        self.plant_context.SetContinuousState(self.system.to_drake_state(x))
        self.visualizer.ForcedPublish(self.visualizer_context)


def _camera_pose(system: "System") -> RigidTransform:
    """Pose of the 2D camera: +x to the right, +z up, positive angles counter-clockwise.

    Our chain model (systems/dynamics.py) and the cart-pole SDFs swing positive
    angles towards +x, viewed from -y. Drake's AcrobotGeometry and PendulumGeometry
    swing them towards -x, so they are viewed from +y (a mirror image of the
    Drake scene, the same picture as our model's).
    """
    if system.drake_model in ("acrobot", "pendulum"):
        return RigidTransform(RotationMatrix.MakeZRotation(np.pi), [0.0, 1.0, 0.0])
    return RigidTransform([0.0, -1.0, 0.0])


def _view_box(system: "System", states: np.ndarray) -> tuple[float, float, float, float]:
    """(xmin, xmax, zmin, zmax) of a side view that keeps the whole motion in sight."""
    if system.chain is None:   # a multibody model: the box around every body origin along the motion
        points = system.dynamics.points(states[:: max(1, len(states) // 200)])
        xs, zs = np.append(points[..., 0].ravel(), 0.0), np.append(points[..., 2].ravel(), 0.0)
        xmin, xmax = float(xs.min()) - _VIEW_MARGIN, float(xs.max()) + _VIEW_MARGIN
        zmin, zmax = float(zs.min()) - _VIEW_MARGIN, float(zs.max()) + _VIEW_MARGIN
        return _aspect(xmin, xmax, zmin, zmax)
    reach = float(np.sum(system.chain.link_length)) + _VIEW_MARGIN
    if system.chain.has_cart:
        lo, hi = float(states[:, 0].min()), float(states[:, 0].max())
        reach_x = reach + 0.15  # half the cart's width
        xmin, xmax = lo - reach_x, hi + reach_x
    else:
        xmin, xmax = -reach, reach
    return _aspect(xmin, xmax, -reach, reach)


def _aspect(xmin: float, xmax: float, zmin: float, zmax: float) -> tuple[float, float, float, float]:
    """Pad the shorter side so the box has a 4:3 aspect and the robot is not stretched."""
    width, height = xmax - xmin, zmax - zmin
    if width < 4 / 3 * height:
        pad = (4 / 3 * height - width) / 2
        xmin, xmax = xmin - pad, xmax + pad
    else:
        pad = (3 / 4 * width - height) / 2
        zmin, zmax = zmin - pad, zmax + pad
    return xmin, xmax, zmin, zmax


class ReplayPage(str):
    """The self-contained HTML page of a replay: a ``str`` (write it, embed it) whose echo in a notebook is the
    replay itself in an iframe, and whose ``repr`` is one line, not megabytes of HTML."""

    path: Path | None = None

    def __repr__(self) -> str:
        where = f", written to {self.path}" if self.path is not None else ""
        return f"<meshcat replay page: {len(self):,} characters{where}>"

    def _repr_html_(self) -> str:
        import html
        return f'<iframe srcdoc="{html.escape(self)}" style="width: 100%; height: 420px; border: 0"></iframe>'


_SHARED_MESHCAT: list[Meshcat] = []


def shared_meshcat() -> Meshcat:
    """The one localhost Meshcat server of this process that replays without a ``meshcat`` argument use
    (started on first use; each replay replaces its ``replay/`` content)."""
    if not _SHARED_MESHCAT:
        _SHARED_MESHCAT.append(start_meshcat())
    return _SHARED_MESHCAT[0]


def replay_html(system: "System", times, states, path: str | Path | None = None,
                meshcat: Meshcat | None = None, fps: float = DEFAULT_FPS) -> ReplayPage:
    """Record a trajectory as a meshcat animation; returns (and writes) a self-contained HTML page.

    ``times`` (T,) strictly increasing seconds, ``states`` (T, n_states) in the
    spec's convention (numpy or torch; e.g. a simulation or a torch env rollout).
    The animation starts at ``times[0]`` and shows, at each of ``fps`` (> 0) frames
    per second, the latest state at or before that frame's time (no interpolation,
    so wrapped angles do not produce spurious spins). The page shows a 2D side view
    of the x-z plane (+x right, +z up) sized to the motion for a 4:3 window; in
    other window shapes meshcat keeps the height and the left edge. The animation
    plays once on load (replay it from "Open Controls" > Animations).

    ``path`` writes the HTML there. ``meshcat`` defaults to this process' one
    localhost server (:func:`shared_meshcat`, started once); a given one keeps its
    other content and gets its ``replay/`` prefix replaced and its animation and
    camera set. The page is a :class:`ReplayPage`: a ``str`` that a notebook shows as
    the replay.
    """
    times, states = _check_trajectory(system, times, states)
    if not fps > 0:
        raise ValueError(f"fps must be > 0, got {fps}")
    if meshcat is None:
        meshcat = shared_meshcat()
    meshcat.Delete("replay")
    scene = _Scene(system, meshcat, fps)
    n_frames = int(np.floor((times[-1] - times[0]) * fps + 1e-9)) + 1
    frame_times = np.arange(n_frames) / fps
    index = np.searchsorted(times - times[0], frame_times + 1e-9, side="right") - 1
    scene.visualizer.StartRecording(set_transforms_while_recording=False)
    for k, i in enumerate(index):
        # Meshcat files a publish at time t under frame floor(t * fps); publishing
        # mid-frame keeps float error (0.58 * 50 = 28.999...) from merging frames.
        scene.publish((k + 0.5) / fps, states[i])
    scene.visualizer.StopRecording()
    scene.visualizer.PublishRecording()
    # Show the first frame's pose even before the animation starts playing.
    scene.publish(0.0, states[0])
    xmin, xmax, zmin, zmax = _view_box(system, states)
    meshcat.Set2dRenderMode(_camera_pose(system), xmin, xmax, zmin, zmax)
    page = ReplayPage(meshcat.StaticHtml())
    if path is not None:
        Path(path).write_text(page)
        page.path = Path(path)
    return page
