"""The seed's section III studies on the virtual cohort (kinematic mode), run by run.

Placeholder header; the study functions follow below.
"""

from __future__ import annotations

import re


def expand_patients(text: str) -> list[str]:
    """Patient specs from a comma list of ``test:0-14``, ``seed:100-120``, ``train:3`` or
    patient paths. Ranges are inclusive."""
    specs = []
    for part in str(text).split(","):
        part = part.strip()
        if not part:
            continue
        m = re.fullmatch(r"(test|train|seed):(\d+)-(\d+)", part)
        if m:
            lo, hi = int(m.group(2)), int(m.group(3))
            if hi < lo:
                raise ValueError(f"--patients: range {part!r} runs backwards")
            specs += [f"{m.group(1)}:{k}" for k in range(lo, hi + 1)]
        elif re.fullmatch(r"(test|train|seed):\d+", part) or "/" in part or "." in part:
            specs.append(part)
        else:
            raise ValueError(f"--patients: cannot read {part!r} (expected test:0-14, "
                             "seed:100-120, train:3 or a patient path)")
    if not specs:
        raise ValueError("--patients: no patients given")
    return specs
