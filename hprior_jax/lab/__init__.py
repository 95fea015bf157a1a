"""The reward-learning lab (`hprior reward-lab`): reward learning decoupled from RL.

An app of its own on top of the methods: it imports `hprior_jax.methods` (their presets,
SURF's config), and no method imports it. Which methods are lab rules is its table, `rules`.

sweep               the RL preset's settings -> a lab run -> results, timing and the report
rules               the rule table: every rule, its credit α, the reference rule
config              the lab's configuration, its rules' credits α and its programs' data types
dataset             a task's fixed episodes (a SAC run's replay buffer), held-out labelled pairs
learn               every (seed, rule) cell trained round by round in one compiled program
rounds              one round of one cell: query, teacher, credit, reward update
surf_round          SURF's round and cells, in a program of its own
seed_world_model    a seed's world model, trained once on the training episodes
world_model_cache   trained world models kept on disk for the next lab of the same data
resume              a lab's state between rounds, to go on after a stop
npz_files           the lab's .npz files, written whole and read leaf by leaf
human_labels        queries from a lab dataset for a person, and the answers back as labels
metrics             reward quality on held-out data
contrasts           the pre-registered contrasts (Holm's correction, equivalence tests)
report              the report against the reference rule at each label budget (`hprior
                    reward-lab report` rebuilds it, or merges several labs')
report_figures      the report's figures: each metric against the label budget
report_notes        the paragraphs a report shows first (does the world model predict?)
"""
