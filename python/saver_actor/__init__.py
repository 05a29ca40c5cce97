"""saver-actor: SAVER actors for any Gymnasium environment.

    from saver_actor import Actor, Connection, EnvDecl, Policy, check_env, provide_samples

Declare which observation entries are the state-aligned position (EnvDecl), check the
env against it (check_env), run an Actor against a `saver learner` (A2C, SAVER or
QRRL) and, for SAVER, let provide_samples feed the pcpn-trainer the transitions its
PCPN is pretrained on; load a trained policy and predict with it (Policy).
"""
from .actor import Actor, Connection, LinkLost, Refused, RunFinished, Summary
from .check import CheckReport, check_env
from .env import EnvDecl, EnvError, factory_function
from .policy import Gaussian, Policy, Quantile, policy_for
from .samples import provide_samples

__all__ = ["Actor", "CheckReport", "Connection", "EnvDecl", "EnvError", "Gaussian", "LinkLost", "Policy",
           "Quantile", "Refused", "RunFinished", "Summary", "check_env", "factory_function", "policy_for",
           "provide_samples"]
