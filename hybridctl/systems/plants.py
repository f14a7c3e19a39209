"""Drake plants for the benchmark systems: the reference dynamics and the viewer.

``acrobot`` -> ``pydrake.examples.AcrobotPlant`` (parameters live in the Context),
``pendulum`` -> ``pydrake.examples.PendulumPlant``, ``multibody:FILE.sdf`` -> a
continuous-time ``MultibodyPlant`` parsed from the template in ``models/`` filled
with the spec's parameters.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path
from string import Template
from typing import Any, Callable

import numpy as np
from pydrake.examples import (AcrobotGeometry, AcrobotParams, AcrobotPlant, PendulumGeometry, PendulumParams,
                              PendulumPlant)
from pydrake.multibody.parsing import Parser
from pydrake.multibody.plant import AddMultibodyPlantSceneGraph, MultibodyPlant
from pydrake.systems.framework import Context, DiagramBuilder, InputPort, OutputPort, System

from ..limits import MAX_MODEL_BYTES
from . import model_files
from .spec import MODELS_DIR

HybridSystem = Any
"""A :class:`hybridctl.systems.System` (not imported: the package imports this module when a plant is asked
for, and an import back, even under ``TYPE_CHECKING``, would make the two a cycle)."""

# sdformat rejects exactly-zero inertias; 1e-20 kg m^2 stands in for a point mass.
_POINT_MASS_INERTIA = 1e-20
# Position of l2 in AcrobotParams (m1, m2, l1, l2, lc1, lc2, Ic1, Ic2, b1, b2, gravity).
_ACROBOT_L2_INDEX = 3


@dataclass
class PlantHandle:
    """A plant added to a builder: its ports and how to put the spec's parameters in a Context."""

    plant: System
    state_output: OutputPort
    actuation_input: InputPort
    apply_parameters: Callable[[Context], None]


def render_model(system: HybridSystem) -> str:
    """The SDF text of a multibody system, with the spec's parameters filled in."""
    kind = system.spec.get("model.drake")
    filename = kind.split(":", 1)[1]
    p = system.chain
    fields = {"cart_mass": repr(float(p.cart_mass))}
    for i in range(p.n_links):
        fields[f"link_mass_{i}"] = repr(float(p.link_mass[i]))
        fields[f"link_length_{i}"] = repr(float(p.link_length[i]))
        fields[f"half_length_{i}"] = repr(float(p.link_length[i]) / 2)
        fields[f"link_com_{i}"] = repr(float(p.link_com[i]))
        fields[f"link_inertia_{i}"] = repr(max(float(p.link_inertia[i]), _POINT_MASS_INERTIA))
    # a template is one of the package's own models (the rendered text's meshes resolve nowhere else):
    # a bare file name, a regular file of bounded size (never a path out of models/, a FIFO or a device)
    if Path(filename).name != filename or not filename.endswith(".sdf"):
        raise ValueError(f"{system.spec.path}: 'model.drake' = {kind!r} must name an .sdf template in the "
                         f"package's models/ folder by its bare file name")
    text = model_files.read_bounded(MODELS_DIR / filename, MAX_MODEL_BYTES, f"models/{filename}").decode()
    try:
        return Template(text).substitute(fields)
    except KeyError as exc:
        raise ValueError(f"models/{filename} uses field {exc} that the spec {system.spec.path} does not provide") from exc


def _acrobot_parameter_setter(system: HybridSystem, plant: AcrobotPlant) -> Callable[[Context], None]:
    def apply(context: Context) -> None:
        _set_acrobot_params_object(system, plant.get_mutable_parameters(context))
    return apply


def _pendulum_parameter_setter(system: HybridSystem, plant: PendulumPlant) -> Callable[[Context], None]:
    p = system.chain
    if p.link_inertia[0] != 0.0 or p.link_com[0] != p.link_length[0]:
        raise ValueError(f"{system.spec.path}: Drake's PendulumPlant is a point mass: "
                         "params.link_com must equal params.link_length and params.link_inertia be 0")

    def apply(context: Context) -> None:
        params = plant.get_mutable_parameters(context)
        params.set_mass(p.link_mass[0]); params.set_length(p.link_length[0])
        params.set_damping(p.joint_damping[0]); params.set_gravity(p.gravity)
    return apply


def _symbolic():
    from . import symbolic
    return symbolic


def input_matrix(system: HybridSystem, plant) -> np.ndarray:
    """S: the plant's actuation input is S u for the system's action u (see ``System.drake_input_matrix``)."""
    if system.family == "multibody":
        return _symbolic().actuator_selection(plant, system.model_request)[0]
    return np.eye(system.n_actions)


class _SpecDefaults:
    """Mixin for Drake's example plants, whose parameters live in the Context: ``CreateDefaultContext`` writes
    the spec's parameters, not Drake's own defaults (an AcrobotPlant's default lc2 is 1.0 and Ic2 0.33;
    the thesis acrobot's are 0.5 and 1.0). A Diagram's context is made in C++ and does not see this: diagrams
    add the plant with ``add_plant``, whose handle writes the parameters."""

    def __init__(self, setter_factory):
        super().__init__()
        self._write_spec_parameters = setter_factory(self)

    def CreateDefaultContext(self):  # noqa: N802 - Drake's name
        """A Context of this plant holding the spec's parameters."""
        context = super().CreateDefaultContext()
        self._write_spec_parameters(context)
        return context


class SpecAcrobotPlant(_SpecDefaults, AcrobotPlant):
    """Drake's AcrobotPlant whose default Context holds the spec's parameters."""


class SpecPendulumPlant(_SpecDefaults, PendulumPlant):
    """Drake's PendulumPlant whose default Context holds the spec's parameters."""


def make_plant(system: HybridSystem):
    """A fresh, unowned Drake plant and the function that writes the spec's parameters into a Context."""
    kind = system.spec.get("model.drake", "multibody")
    if kind == "acrobot":
        plant = SpecAcrobotPlant(lambda plant: _acrobot_parameter_setter(system, plant))
        return plant, plant._write_spec_parameters
    if kind == "pendulum":
        plant = SpecPendulumPlant(lambda plant: _pendulum_parameter_setter(system, plant))
        return plant, plant._write_spec_parameters
    if system.family == "multibody":
        return _symbolic().parse_plant(system.model_request), (lambda context: None)
    if kind.startswith("multibody:"):
        plant = MultibodyPlant(0.0)
        _parse_model(system, plant)
        return plant, (lambda context: None)
    raise ValueError(f"{system.spec.path}: 'model.drake' must be 'acrobot', 'pendulum' or "
                     f"'multibody:FILE.sdf', got {kind!r}")


def _parse_model(system: HybridSystem, plant: MultibodyPlant) -> None:
    Parser(plant).AddModelsFromString(render_model(system), "sdf")
    plant.Finalize()


def _ports(plant) -> tuple[OutputPort, InputPort]:
    if isinstance(plant, MultibodyPlant):
        return plant.get_state_output_port(), plant.get_actuation_input_port()
    return plant.get_output_port(0), plant.get_input_port(0)


def add_plant(system: HybridSystem, builder: DiagramBuilder, with_geometry: bool = False):
    """Add the system's Drake plant to ``builder``; returns (PlantHandle, scene_graph or None).

    With ``with_geometry`` a SceneGraph is added and the plant's geometry registered,
    ready for a MeshcatVisualizer.
    """
    scene_graph = None
    if system.family == "multibody" and with_geometry:
        plant, scene_graph = AddMultibodyPlantSceneGraph(builder, 0.0)
        _symbolic().parse_plant(system.model_request, plant)
        setter = lambda context: None  # noqa: E731 - the model file holds the parameters
    elif system.spec.get("model.drake", "").startswith("multibody:") and with_geometry:
        plant, scene_graph = AddMultibodyPlantSceneGraph(builder, 0.0)
        _parse_model(system, plant)
        setter = lambda context: None  # noqa: E731 - parameters are baked into the model
    else:
        plant, setter = make_plant(system)
        builder.AddSystem(plant)
    state_output, actuation_input = _ports(plant)
    if with_geometry and scene_graph is None:
        from pydrake.geometry import SceneGraph
        scene_graph = builder.AddSystem(SceneGraph())
        if isinstance(plant, AcrobotPlant):
            params = AcrobotParams()
            _set_acrobot_params_object(system, params)
            AcrobotGeometry.AddToBuilder(builder, state_output, params, scene_graph)
        else:
            if system.chain.link_length[0] != PendulumParams().length():
                warnings.warn(f"{system.name}: Drake's PendulumGeometry draws its default length "
                              f"{PendulumParams().length()} m, not {system.chain.link_length[0]} m", stacklevel=2)
            PendulumGeometry.AddToBuilder(builder, state_output, scene_graph)
    if system.family == "multibody":
        selection = input_matrix(system, plant)
        if selection.shape[0] != selection.shape[1] or not np.array_equal(selection, np.eye(selection.shape[0])):
            # the spec actuates a subset (or another order) of the model's actuators: u -> S u
            from pydrake.systems.primitives import MatrixGain
            gain = builder.AddSystem(MatrixGain(selection))
            builder.Connect(gain.get_output_port(), actuation_input)
            actuation_input = gain.get_input_port()
    plant.set_name("plant")
    return PlantHandle(plant, state_output, actuation_input, setter), scene_graph


def _set_acrobot_params_object(system: HybridSystem, params) -> None:
    p = system.chain
    params.set_m1(p.link_mass[0]); params.set_m2(p.link_mass[1])
    params.set_l1(p.link_length[0])
    params.set_lc1(p.link_com[0]); params.set_lc2(p.link_com[1])
    params.set_Ic1(p.link_inertia[0]); params.set_Ic2(p.link_inertia[1])
    params.set_b1(p.joint_damping[0]); params.set_b2(p.joint_damping[1])
    params.set_gravity(p.gravity)
    # l2 only sets the drawn length of link 2 (AcrobotParams has no setter for it).
    params.SetAtIndex(_ACROBOT_L2_INDEX, p.link_length[1])


def drake_state_offset(system: HybridSystem) -> np.ndarray:
    """x_drake - x (see ``System.drake_state_offset``)."""
    return system.drake_state_offset()


def make_plant_parameter_setter(system: HybridSystem, plant) -> Callable[[Context], None]:
    """The function that writes the spec's parameters into a Context of ``plant``."""
    if isinstance(plant, AcrobotPlant):
        return _acrobot_parameter_setter(system, plant)
    if isinstance(plant, PendulumPlant):
        return _pendulum_parameter_setter(system, plant)
    return lambda context: None


def actuation_port(plant) -> InputPort:
    """The plant's actuation input port."""
    return _ports(plant)[1]
