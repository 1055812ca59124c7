"""Testing helpers for users of torm: the pytest smoke-trial plugin (:mod:`torm.testing.plugin`) and test
doubles of the real hardware on loopback (:mod:`torm.testing.fake_rosbridge`: rosbridge + a
joint_trajectory_controller model; :mod:`torm.testing.fake_robotiq`: a Modbus RTU Robotiq 2F-85), which
need the ``hardware`` extra (websockets)."""
