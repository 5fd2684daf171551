"""Reliability and safety: fault injection, patient motion, the campaign, bad-input checks."""
