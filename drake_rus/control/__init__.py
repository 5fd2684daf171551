"""Control: orientation alignment, force PD, position P, null-space diff IK, supervisor, safety."""
