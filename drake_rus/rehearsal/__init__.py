"""Software-in-the-loop rehearsal: the unchanged hardware scan against a simulated robot,
patient and ultrasound machine in another process, over the real wire protocol.

- ``core``: pure functions (command age statistics, stop reaction, PIVOT-like motion, the
  scan side's overrides, kidney errors, network isolation);
- ``mjpeg``: the machine's video output as MJPEG over HTTP on 127.0.0.1;
- ``wiretap``: every LCM packet of a channel with its kernel receive time;
- ``sim``: the simulated station behind drake-franka-driver's wire, paced at real time;
- ``sim_process``: that as a process (``python -m drake_rus.rehearsal.sim_process``);
- ``run``: the sim process handle and ``RunRehearsal`` (the scan in this process);
- ``drill``: the stop drill (SIGTERM to ``drake-rus scan`` mid-PIVOT, the robot's reaction);
- ``cli``: ``drake-rus rehearse``.

Nothing in the product imports this package (tests/test_architecture.py).
"""
