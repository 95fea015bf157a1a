"""The package version (one place: `hprior_jax.__version__`, provenance, `--version`)."""
__version__ = "0.1.0"
