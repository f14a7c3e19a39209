"""Reproduction drivers: one module per thesis table or figure, each run as
``python -m hybridctl.reproduce.NAME [args]`` (``--help`` lists its arguments) from the repository root.

Each writes its record (JSON, with CSV or PNG beside it where it has them) under ``results/chN/``,
relative to the working directory (``--out`` or ``--record`` changes it), and resumes from the
checkpoints of its work folder (``results/INDEX.md`` lists them). Records hold paths relative to the
working directory, never the machine's absolute ones. The notebooks and the docs read these records.

Ch. 3, switched SAC:

- :mod:`~hybridctl.reproduce.ch3_results`: Table 3.1's SSAC and SAC rows, the training curves and the
  balance maps (Figs. 3.4-3.6) of ``hybridctl train`` runs -> ``results/ch3/results.json``;
- :mod:`~hybridctl.reproduce.sb3_baselines`: Table 3.1's Stable-Baselines3 rows and Fig. 3.3 (PPO, A2C,
  TRPO, SAC, TD3 with the RL Zoo's settings) -> ``results/ch3/sb3_baselines/``;
- :mod:`~hybridctl.reproduce.cartpole_record`: the shipped SSAC cart-poles in Drake and their balance
  maps -> ``results/ch3/cartpole/``, ``results/ch3/double_cartpole/``.

Ch. 4, trajectory dimension:

- :mod:`~hybridctl.reproduce.table41`: Table 4.1 at a reduced scale (``--train ENV SEED`` trains the ARS
  runs, then the evaluation) -> ``results/ch4/results.json``;
- :mod:`~hybridctl.reproduce.table44`: Table 4.4 with the thesis' protocol (grid search, failure rates)
  -> ``results/ch4/table44.json``, ``table44-walker2d.json``;
- :mod:`~hybridctl.reproduce.walker_seeds`: the Walker2d seeds Table 4.4 needs -> ``results/ch4/walker_seeds.json``.

Ch. 5, reachable meshes and MFPT:

- :mod:`~hybridctl.reproduce.hopper`: hopper meshes, MFPT against Monte Carlo -> ``results/ch5/hopper.json``;
- :mod:`~hybridctl.reproduce.hopper_error`: where the mesh's MFPT error comes from -> ``results/ch5/hopper_error.json``;
- :mod:`~hybridctl.reproduce.hopper_ulam`: several samples per box -> ``results/ch5/hopper_ulam.json``;
- :mod:`~hybridctl.reproduce.table51`: Table 5.1, mesh sizes of four training regimes -> ``results/ch5/table51.json``.

Ch. 6, fine-tuning (Tables 6.1-6.3):

- :mod:`~hybridctl.reproduce.ch6_agents`: the Stable-Baselines3 agents the fine-tuning starts from
  -> ``runs/finetune-agents``, ``results/ch6/agents.json``;
- :mod:`~hybridctl.reproduce.ch6_finetune`: fine-tune them, train them on, collect -> ``results/ch6/results.json``.

Ch. 7, analytic policy gradients:

- :mod:`~hybridctl.reproduce.fig71`: Fig. 7.1, return landscape and BPTT gradient norms -> ``results/ch7/fig71.json``;
- :mod:`~hybridctl.reproduce.table71`: Tables 7.1 / 7.2, the method study -> ``results/ch7/table71.json``;
- :mod:`~hybridctl.reproduce.papg_takeover_seeds`: the shipped PAPG cart-pole recipe over seeds
  -> ``results/ch7/papg-takeover-cartpole.json``.

Every chain: :mod:`~hybridctl.reproduce.matrix`, the learner x system matrix (every shipped swing-up
and the classical baselines on Drake balance maps near hanging down) -> ``results/matrix/``.

Your robot: :mod:`~hybridctl.reproduce.fit_robots`, ``hybridctl fit`` on the shipped Drake models from their model
files and on two made-up robots -> ``results/your_robot/fit/ROBOT.json``.

:mod:`~hybridctl.reproduce.common` holds what they share (the machine record, paths as recorded).
This room sits at the top beside ``cli``: it may import every room below it; nothing imports it.
"""
