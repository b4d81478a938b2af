"""The typed data the agent passes around: network inputs, rollouts, agent and training state.

Sequences are time-major: `[T, B, ...]`. A rollout of T steps holds T+1 network
inputs (the last one is the state the returns bootstrap from) and T steps.
"""

from __future__ import annotations

from typing import Any, Optional

import chex
import jax.numpy as jnp
from flax import struct


@struct.dataclass
class Inputs:
    """What the network reads at one step, per agent: leaves [B] (or [T+1, B]).

    rgb [..., H, W, 3] uint8 observation; target [...] int32 index of the target image
    (into the environment's `target_images()`); prev_action int32; prev_reward float32;
    reset bool: an episode starts here, the memory core is cleared before this step.
    """

    rgb: jnp.ndarray
    target: jnp.ndarray
    prev_action: jnp.ndarray
    prev_reward: jnp.ndarray
    reset: jnp.ndarray


@struct.dataclass
class Transition:
    """A rollout of T steps in B environments (what the replay buffer stores).

    The network inputs of T+1 steps, [T+1, B] (fields as in `Inputs`; the last step is
    the state the returns bootstrap from), and of each of the T steps taken: action
    int32 [T, B], reward float32 [T, B], terminated bool [T, B] (the step reached the
    goal: a terminal state), truncated bool [T, B] (the episode hit its time limit).
    """

    rgb: jnp.ndarray
    target: jnp.ndarray
    prev_action: jnp.ndarray
    prev_reward: jnp.ndarray
    reset: jnp.ndarray
    action: jnp.ndarray
    reward: jnp.ndarray
    terminated: jnp.ndarray
    truncated: jnp.ndarray

    @property
    def inputs(self) -> Inputs:
        return Inputs(self.rgb, self.target, self.prev_action, self.prev_reward, self.reset)

    def check(self, steps: int, batch: int, image_size: int) -> None:
        """Assert (chex, when traced) that this is a rollout of `steps` steps in `batch`
        environments with `image_size` square images, each field of its dtype."""
        chex.assert_shape(self.rgb, (steps + 1, batch, image_size, image_size, 3))
        chex.assert_type(self.rgb, jnp.uint8)
        chex.assert_shape([self.target, self.prev_action, self.prev_reward, self.reset], (steps + 1, batch))
        chex.assert_shape([self.action, self.reward, self.terminated, self.truncated], (steps, batch))
        chex.assert_type([self.target, self.prev_action, self.action, self.prev_reward, self.reward],
                         [int, int, int, float, float])
        chex.assert_type([self.reset, self.terminated, self.truncated], bool)

    @property
    def done(self):
        """[T, B] bool: the step ended an episode."""
        return self.terminated | self.truncated

    @classmethod
    def of(cls, inputs: Inputs, action, reward, terminated, truncated) -> "Transition":
        return cls(inputs.rgb, inputs.target, inputs.prev_action, inputs.prev_reward, inputs.reset, action, reward,
                   terminated, truncated)


@struct.dataclass
class FrameTruth:
    """Depth and segmentation ground truth of frames at auxiliary resolution [..., a, a]:
    depth in metres * DEPTH_SCALE; segmentation class colours [..., a, a, 3] in [0, 1]
    (or class ids [..., a, a]). None where the loss is off."""

    depth: Optional[jnp.ndarray] = None
    segmentation: Optional[jnp.ndarray] = None


@struct.dataclass
class AgentState:
    """What the agent carries between steps, per environment [B]."""

    carry: Any  # memory core state
    prev_action: jnp.ndarray  # int32
    prev_reward: jnp.ndarray  # float32
    reset: jnp.ndarray  # bool: clear the core state before the next step (a new episode began)


@struct.dataclass
class TrainState:
    """Everything a run needs to continue exactly: checkpointed whole."""

    params: Any
    opt_state: Any
    env_state: Any
    agent: AgentState
    replay: Any  # replay.Replay of Transitions, or None when no replay loss is on
    key: jnp.ndarray  # uint32 [2]
    update: jnp.ndarray  # int32: updates done so far
