"""The tiny learner the tests share: 4 environments, 16x16 images, the unculled renderer
(fastest to compile), 4-step rollouts, a small network."""

TINY_LEARNER = [
    "env.num_envs=4",
    "env.render.image_size=16",
    "env.render.culling=false",
    "env.goals_per_scene=2",
    "train.rollout_length=4",
    "train.replay_size=8",
    "train.replay_batch=2",
    "agent.conv_channels=[4,8,8,8]",
    "agent.dense_size=16",
    "agent.core_size=16",
]

# A run of the tiny learner in one small room with 10-step episodes (tests of what the
# MuJoCo environment does: evaluation, the oracle, held-out houses).
TINY_ROOM = TINY_LEARNER + ["env.scene.kind=room", "env.scene.num_scenes=1", "env.max_episode_steps=10"]
# The tiny learner in the synthetic environment (env/synthetic.py), 10-step episodes: the
# tests of the agent, the update, checkpoints and scaling, where the environment is not
# what is tested (it compiles in a fraction of the time).
TINY_SYNTHETIC = TINY_LEARNER + ["env.kind=synthetic", "env.scene.num_scenes=1", "env.max_episode_steps=10"]
# ... logged every update and checkpointed every second one.
TINY_RUN = TINY_SYNTHETIC + ["train.log_every=1", "train.checkpoint_every=2"]
