"""Learning from demonstration (Schneider & Ertel, IROS 2010) on plain arrays, for any robot.

Public API (one module each; ``gym_coffee`` is imported only by :mod:`.adapters.coffee`):

* :mod:`lgp_policy.lfd.demonstrations`: ``Trajectory(time, state, frames, gripper=None,
  actions=None, events={}, success=True)`` and ``TrajectorySet`` (demonstrations naming the same
  frames). ``frames = {name: (position (n, d) or (d,), rotation (n, d, d) or (d, d) or a scipy
  Rotation)}``, ``d`` = 2 or 3, any number of frames with any names.
* :mod:`lgp_policy.lfd.robots`: the ``RobotModel`` protocol (``n_joints``, ``dim``,
  ``has_orientation``, ``joint_lower``/``joint_upper``, batched ``forward_pose(q) -> (p, R)``
  and geometric ``jacobian(q)``), ``CartesianPointRobot(dim)``; the ``ActionMap`` protocol
  (``max_step``, ``__call__(q, step, gripper) -> action``) with ``JointDeltaAction`` and
  ``CartesianDeltaAction``; ``GripperSpec(closed, open)``.
* :mod:`lgp_policy.lfd.adapters`: the ``ObservationAdapter`` protocol (``read(obs (n, D)) ->
  Observed(time, state, frames, valid, events)`` plus ``name``, ``obs_dim``, ``frame_names``,
  ``robot``, ``action_map``, ``gripper``, ``control_dt``), ``ArrayAdapter`` (from index slices);
  :mod:`lgp_policy.lfd.adapters.coffee`: ``CoffeeAdapter``, ``PandaModel``, ``to_trajectories``.
* :mod:`lgp_policy.lfd.encoding`: ``DemonstrationEncoder`` (time-indexed GPs per frame).
* :mod:`lgp_policy.lfd.reproduction`: Algorithm 3 for a batch (``reproduction_step``,
  ``frame_targets``, ``damped_pseudoinverse``, ``limit_step``).
* :mod:`lgp_policy.lfd.policy`: ``GPDemonstrationPolicy(robot=None, adapter=None, ...)`` with
  ``fit(demos, allow_failed=False)``, SB3's ``predict(obs, state, episode_start,
  deterministic)`` (batched in one pass; ``state`` is a ``PolicyState``: online frame filter and
  event-driven phase), ``predict_distribution``, ``phase``, ``constraint_report``,
  ``save(path, overwrite=False)`` / ``load(path_or_bytesio, robot=None, adapter=None)``.

Walk-through: ``docs/own-robot.md``; decisions and their measurements: ``docs/design-lfd.md``.
"""
