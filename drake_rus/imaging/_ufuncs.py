"""numpy's ``clip`` ufunc, for the per-frame imaging chain.

``np.clip`` checks its arguments in Python before it calls this ufunc (about 7 us a call,
twice the work itself on a 40k-pixel frame); ``clip(a, lo, hi, out=a)`` gives the same values
(NaN stays NaN). Falls back to ``np.clip`` where the ufunc is not found.
"""

import numpy as np

try:
    from numpy._core.umath import clip
except ImportError:  # numpy < 2
    try:
        from numpy.core.umath import clip
    except ImportError:
        clip = np.clip

if not isinstance(clip, np.ufunc):
    clip = np.clip
