"""Control: orientation alignment, force PD, position P, null-space diff IK, supervisor, safety.

Pure laws: ``laws`` (eq. 1-12), ``scan`` (eq. 17, 20-23 and the supervisor's state machine),
``safety`` (fault checks, command limits, stop and retract). LeafSystems: ``systems``.
Wiring: ``diagram.AddController`` / ``diagram.BuildClosedLoop``. Gains and limits:
``config`` (the scenario's ``controller:`` and ``safety:`` sections).
"""
