"""`camera_vote`: one grasp's P(slip) from the P(slip) of each of its cameras, as the trial network
(:mod:`fv_algos.trial_net`) judges all the cameras of a trial together. No torch: the slip fusion
node imports it."""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.special import expit, logit

LOGIT_LIMIT = 36.0  # |logit| a float64 P(slip) holds (1 - P rounds to 0 beyond it); beyond counts as this


def camera_vote(probabilities: Sequence[float]) -> float:
    """P(slip) of a grasp from its cameras' P(slip), each judged alone (one
    `fv_algos.grasp_judge.GraspJudge` per camera): what the trial network says of the cameras
    together. Its logit is the mean of the cameras' logits, since the network averages the cameras'
    pooled features and its head is linear. The logits are taken back from float64 probabilities,
    exactly while |logit| < `LOGIT_LIMIT`."""
    if len(probabilities) == 0:
        raise ValueError("camera_vote needs at least one camera's P(slip)")
    with np.errstate(divide="ignore"):  # P 0 or 1: logit -inf or +inf, clipped
        z = np.clip(logit(np.asarray(probabilities, np.float64)), -LOGIT_LIMIT, LOGIT_LIMIT)
    return float(expit(z.mean()))
