"""hprior_jax: Hindsight PRIOR and PbRL baselines in JAX/Flax on MJX tasks."""
from tasks import _xla_flags  # noqa: F401  (sets XLA_FLAGS before jax is imported)

__version__ = "0.1.0"


def load_reward(path):
    """A learned reward exported by `hprior export`, as a pure function (obs, action) -> r̂."""
    from hprior_jax.export import load_reward as load

    return load(path)


def load_policy(path):
    """A policy exported by `hprior export`, as a pure function obs -> action."""
    from hprior_jax.export import load_policy as load

    return load(path)
