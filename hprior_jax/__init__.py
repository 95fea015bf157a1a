"""hprior_jax: Hindsight PRIOR and PbRL baselines in JAX/Flax on MJX tasks."""
from tasks import _xla_flags  # noqa: F401  (sets XLA_FLAGS before jax is imported)

from hprior_jax._version import __version__  # noqa: F401
from hprior_jax.api import Env, Evaluation, evaluate_policy, make_env, train
from hprior_jax.export import export_seed, load_policy, load_reward

__all__ = ["Env", "Evaluation", "evaluate_policy", "export_seed", "load_policy", "load_reward",
           "make_env", "train"]
