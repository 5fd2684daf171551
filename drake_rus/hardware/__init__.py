"""drake-rus hardware: the station on a real FR3 and ultrasound machine.

- ``config``: the scenario section ``hardware_interface`` (HardwareConfig);
- ``core``: pure functions (torque sign, wall-clock stamps, command guard, watchdog, crop,
  probe weight, collision thresholds, loop timing statistics);
- ``franky_backend``: the FR3 through franky-control (libfranka 0.21): collision thresholds,
  load, error-recovery policy at connection;
- ``video``: the capture thread (devices, files, stream URLs), the probe pose history, the
  diagram clock, the video latency estimate;
- ``image_calibration``: pixels <-> probe frame per depth preset (file, fit, map);
- ``systems``: thin LeafSystems (command guard, robot interface, LCM status latch and
  stamper, probe load compensation, frame grabber);
- ``station``: ``MakeHardwareStation``, ``HardwareSession``, ``RunHardware``;
- ``lcm_sim_driver``: a simulated drake-franka-driver (PandaCommandReceiver /
  PandaStatusSender) for tests and rehearsal;
- ``calibration``: pivot calibration of the probe tip;
- ``cli``: ``drake-rus hardware check | pivot | grab | calibrate-image | calibrate-latency``.

See docs/hardware_bringup.md.
"""
