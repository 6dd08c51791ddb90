"""Recognisable wrong implementations of this lesson's steps (the lesson format's ``mistakes.py``).

The grader runs one of these on a check's inputs when the student's result fails, and gives the
hint of tasks.toml when the student's result is what the mistake computes. Each is built from the
lab's own functions, so it is exact by construction.
"""

import numpy as np

from lab.modules.epipolar import essential_candidates


def translation_from_right_null_vector(E):
    """t taken from V's last column (E's right null vector, R^T t) instead of U's (its left null vector, t).

    The lab's four candidates with their translation replaced, V^T turned into a rotation as the
    lab does before reading it.
    """
    candidates = essential_candidates(E)
    Vt = np.linalg.svd(np.asarray(E, dtype=np.float64))[2]
    v = -Vt[2] if np.linalg.det(Vt) < 0 else Vt[2]
    candidates[:, :, 3] = np.array([1.0, 1.0, -1.0, -1.0])[:, None] * v
    return candidates
