"""The arm as described by its URDF: links, joints and peg (:mod:`~lolgps_torch.robot.arm`),
batched forward kinematics of the peg's points (:mod:`~lolgps_torch.robot.kinematics`) and the
placement of the task in the arm's workspace (:mod:`~lolgps_torch.robot.placement`).

Both the simulator (:mod:`lolgps_torch.sim`) and the cost (:mod:`lolgps_torch.cost`) build on
this package; it imports neither.
"""
