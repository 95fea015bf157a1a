"""One module per `hprior` command group; `hprior_jax.cli` dispatches to them."""
