"""``hybridctl fit`` on the robots of docs/your_robot.md's table: the shipped Drake models from their model files
alone, and two robots the project never saw (made-up parameters, written here). One robot per call; the record
(``results/your_robot/fit/ROBOT.json``: command, seed, budget, minutes, machine, every stage's seconds, the Drake
maps, the gate kept) is built from the fit's report, and the run folder (checkpoint included) stays under --out.

    python -m hybridctl.reproduce.fit_robots pendubot --out runs/fit-robots/pendubot --budget 20
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

from hybridctl.experiments.fit import fit
from hybridctl.systems.spec import DATA_DIR

from .common import RESULTS, command_line, emit, machine_info, recorded_path

__all__ = ["ROBOTS", "MADE_UP", "SHIPPED", "RENDERED", "model_file", "rendered_model", "main"]

MADE_UP = {
    # the shoulder actuated (6 N m), the elbow free: tests/test_fit.py's pendubot
    "pendubot": """<?xml version="1.0"?>
<robot name="pendubot">
  <link name="base"/>
  <link name="link1"><inertial><origin xyz="0 0 -0.2"/><mass value="0.8"/>
    <inertia ixx="0.02" ixy="0" ixz="0" iyy="0.02" iyz="0" izz="1e-6"/></inertial></link>
  <link name="link2"><inertial><origin xyz="0 0 -0.25"/><mass value="0.5"/>
    <inertia ixx="0.015" ixy="0" ixz="0" iyy="0.015" iyz="0" izz="1e-6"/></inertial></link>
  <joint name="base_weld" type="fixed"><parent link="world"/><child link="base"/></joint>
  <joint name="shoulder" type="continuous"><parent link="base"/><child link="link1"/><axis xyz="0 -1 0"/>
    <limit effort="6.0" velocity="100"/></joint>
  <joint name="elbow" type="continuous"><parent link="link1"/><child link="link2"/><origin xyz="0 0 -0.4"/>
    <axis xyz="0 -1 0"/></joint>
  <transmission type="SimpleTransmission" name="t1"><actuator name="m1"/><joint name="shoulder"/>
    <mechanicalReduction>1</mechanicalReduction></transmission>
</robot>
""",
    # a 1 kg cart pushed along x (10 N), a light 1.5 m pole (0.1 kg, a uniform rod) on a free hinge
    "cart_long_pole": """<?xml version="1.0"?>
<robot name="cart_long_pole">
  <link name="rail"/>
  <link name="cart"><inertial><mass value="1.0"/>
    <inertia ixx="0.01" ixy="0" ixz="0" iyy="0.01" iyz="0" izz="0.01"/></inertial></link>
  <link name="pole"><inertial><origin xyz="0 0 -0.75"/><mass value="0.1"/>
    <inertia ixx="0.01875" ixy="0" ixz="0" iyy="0.01875" iyz="0" izz="1e-6"/></inertial></link>
  <joint name="rail_weld" type="fixed"><parent link="world"/><child link="rail"/></joint>
  <joint name="slider" type="prismatic"><parent link="rail"/><child link="cart"/><axis xyz="1 0 0"/>
    <limit effort="10.0" velocity="100"/></joint>
  <joint name="hinge" type="continuous"><parent link="cart"/><child link="pole"/><axis xyz="0 -1 0"/></joint>
  <transmission type="SimpleTransmission" name="t1"><actuator name="m1"/><joint name="slider"/>
    <mechanicalReduction>1</mechanicalReduction></transmission>
</robot>
""",
}
"""Robots the project never saw: (name -> URDF text), written next to the run folder."""

SHIPPED = {"acrobot_urdf": "acrobot.urdf", "furuta": "furuta.urdf", "reaction_wheel": "reaction_wheel.urdf"}
"""Shipped Drake models fitted from their model file alone (the package's copies)."""

RENDERED = {"cartpole": "cart_slider", "double_cartpole": "cart_slider"}
"""The chain robots whose Drake model is an SDF template (robot -> its actuated slider joint): fitted from the
template rendered with the spec's parameters, the slider's effort limit set to the spec's ``action.limit`` (a
template leaves the limit to the spec; a model file a user brings carries its own)."""
ROBOTS = (*MADE_UP, *SHIPPED, *RENDERED)


def model_file(robot: str, folder: Path) -> Path:
    """The model file of ``robot``: a made-up or rendered one written into ``folder``, else the package's own copy."""
    if robot in MADE_UP or robot in RENDERED:
        folder.mkdir(parents=True, exist_ok=True)
        path = folder / (f"{robot}.urdf" if robot in MADE_UP else f"{robot}.sdf")
        path.write_text(MADE_UP[robot] if robot in MADE_UP else rendered_model(robot))
        return path
    return DATA_DIR / "models" / SHIPPED[robot]


def rendered_model(robot: str) -> str:
    """The SDF text of a shipped chain robot (:data:`RENDERED`): its template with the spec's parameters and the
    spec's action limit as the slider's ``<effort>`` (the only actuator; every hinge keeps its effort 0)."""
    from xml.etree import ElementTree

    from hybridctl.systems import load
    from hybridctl.systems.plants import render_model

    system = load(robot)
    root = ElementTree.fromstring(render_model(system))
    slider = root.find(f".//joint[@name='{RENDERED[robot]}']")
    if slider is None or slider.get("type") != "prismatic":
        raise ValueError(f"models/{robot}.sdf has no prismatic joint {RENDERED[robot]!r}")
    axis = slider.find("axis")
    limit = axis.find("limit")
    if limit is None:
        limit = ElementTree.SubElement(axis, "limit")
    effort = limit.find("effort")
    if effort is None:
        effort = ElementTree.SubElement(limit, "effort")
    effort.text = repr(float(system.action_limit))
    return '<?xml version="1.0"?>\n' + ElementTree.tostring(root, encoding="unicode") + "\n"


def main(argv: list[str] | None = None) -> int:
    """Fit one robot and write its record."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("robot", choices=ROBOTS)
    parser.add_argument("--out", required=True, help="the fit's folder (its model file goes beside it)")
    parser.add_argument("--budget", type=float, default=20.0, help="minutes (default 20)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--resume", action="store_true")
    parser.add_argument("--record", default=None, help="default results/your_robot/fit/ROBOT.json")
    args = parser.parse_args(argv)
    out = Path(args.out)
    model = model_file(args.robot, out.parent / "models")
    start = time.perf_counter()
    result = fit(model, out, budget_minutes=args.budget, seed=args.seed, resume=args.resume,
                 command=command_line("fit_robots", argv))
    report = result.report
    record = {
        "robot": args.robot, "command": command_line("fit_robots", argv), "seed": args.seed,
        "budget_minutes": args.budget, "minutes": (time.perf_counter() - start) / 60,
        "stage_minutes": sum(s["seconds"] for s in report["stages"]) / 60,   # every stage's own run, resumed or not
        "model_file": f"models/{SHIPPED[args.robot]}" if args.robot in SHIPPED else recorded_path(model),
        "model_sha256": report["model_sha256"], "run_folder": recorded_path(out),
        "stages": [{"name": s["name"], "seconds": s["seconds"], "cached": s["cached"]} for s in report["stages"]],
        "goal": result.stages["model"]["goal"], "hold_s": result.stages["lqr"]["hold_s"],
        "swingup_s": result.stages["swingup"]["duration_s"],
        "learned_gate_works": result.stages["learned_gate"]["works"],
        "learner_steps": result.stages["learner"]["steps"],
        "learner_eval_success_rate": result.stages["learner"]["eval_success_rate"],
        "learner_stopped_full": result.stages["learner"].get("stopped_full"),
        "swingup_period_s": result.stages["swingup"]["swingup_period"],
        "tracked_by_period": result.stages["swingup"].get("tracked"),
        "clone": clone_summary(result.stages.get("clone")),
        "checkpoint": report["controller"].get("checkpoint"), "checkpoint_why": report["controller"].get("checkpoint_why"),
        "gate": report["controller"]["gate"], "gate_why": report["controller"]["why"],
        "torch_maps": result.stages["verify"]["torch_maps"], "drake_maps": report["controller"]["drake_maps"],
        "from_hanging_down": {k: report["replay"].get(k) for k in ("balanced", "first_balance_time")},
        "load_average_end": list(os.getloadavg()), "machine": machine_info(),
    }
    emit(record, Path(args.record) if args.record else RESULTS / "your_robot" / "fit" / f"{args.robot}.json")
    return 0


def clone_summary(clone: dict | None) -> dict | None:
    """The clone stage's record: whether it cloned, the tracker's and the kept clone's held-out shares, the rounds."""
    if clone is None:
        return None
    keys = ("cloned", "tracker_fraction", "fraction", "kept_round", "test_starts", "why")
    return {**{k: clone.get(k) for k in keys},
            "rounds": [{k: r[k] for k in ("round", "samples", "fraction", "seconds")} for r in clone.get("rounds", [])]}


if __name__ == "__main__":
    raise SystemExit(main())
