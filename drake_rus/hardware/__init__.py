"""drake-rus hardware: the station on a real FR3 and ultrasound machine.

- ``config``: the scenario section ``hardware_interface`` (HardwareConfig);
- ``core``: pure functions (torque sign, wall-clock stamps, command guard, watchdog, crop);
- ``franky_backend``: the FR3 through franky-control (libfranka 0.21);
- ``systems``: thin LeafSystems (command guard, robot interface, LCM status latch and
  stamper, frame grabber);
- ``station``: ``MakeHardwareStation``, ``HardwareSession``, ``RunHardware``;
- ``lcm_sim_driver``: a simulated drake-franka-driver (PandaCommandReceiver /
  PandaStatusSender) for tests and rehearsal;
- ``calibration``: pivot calibration of the probe tip;
- ``cli``: ``drake-rus hardware check`` and the scripted free-space motion.

See docs/hardware_bringup.md.
"""
