"""The reward-learning lab (`hprior reward-lab`): reward learning decoupled from RL.

dataset  a task's fixed episodes (a SAC run's replay buffer) and held-out labelled pairs
learn    every (seed, rule) cell trained round by round in one compiled program
metrics  reward quality on held-out data
sweep    the RL preset's settings -> a lab run -> results, timing and the report
"""
