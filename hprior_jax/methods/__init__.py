"""Methods as plug-ins: one module each, listed in `registry` (the only list of names).

The methods know nothing of the reward-learning lab (`hprior_jax.lab`, `hprior reward-lab`):
the lab imports them, never the other way (import-linter's layers, pyproject.toml). Which
methods are lab rules, with which credit α, is the lab's own table (`hprior_jax.lab.rules`).
"""
