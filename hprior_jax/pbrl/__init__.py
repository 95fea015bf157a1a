"""Preference-based RL building blocks (pure, jit/vmap-able, static shapes).

teacher:       B-Pref scripted teacher (labels from true rewards)
query:         candidate segment pairs + uniform / disagreement / entropy selection
preference:    Bradley-Terry loss, reward terms, reward-training epochs with early stop
relabel:       rewrite a replay buffer's rewards with the ensemble mean
state_entropy: k-NN state-entropy intrinsic reward + running mean/std
The reward ensemble lives in hprior_jax.networks.reward_ensemble and the label store in
hprior_jax.buffers.preferences; the methods that use these are in hprior_jax.methods.
"""
