"""The training loop: a run's state, the compiled chunks and the host loop between them.

state        RunState: the whole run as one pytree, every leaf with a leading seed axis
engine       the compiled `jit(vmap(chunk))` programs: env, SAC and the method's hooks
host         the loop between programs: schedule, NaN guard, logs, evaluation, checkpoints
programs     compiled programs by name, ahead of time or in a background thread
devices      the seed axis over devices (one mesh axis), and results fetched to the host
checkpoints  saving and restoring a run's checkpoints
run_files    the files of a run directory the loop writes besides checkpoints and logs
episodes     whole episodes of a policy as physics states, and evaluation videos
progress     the progress bar and the wall time of each part of an iteration
stopping     how a run stops early: Ctrl-C, a person's round, a loss no longer finite

A method (`hprior_jax.methods`) imports only `state` and `devices.fetch` from here; a run
directory's configuration is read and written by `hprior_jax.runs`.
"""
