"""The experiments: each a configuration of `configs/` and its variants, as data.

`EXPERIMENTS` names each comparison: a configuration (`configs/NAME_cpu.yaml` or
`configs/NAME.yaml` by scale, `Experiment.config_path`, with the overrides of its task,
`Experiment.setting`) and its variants (`Variant`:
configuration overrides, pre-training). The override constants (`NO_VN`, `NO_UNREAL`,
`NO_RP`, `CLIP_40`, `BLIND`, `NAVIGATION`, `AUTHORS_LOSSES`, `AUTHORS_NETWORK`) are the settings the
variants share. Nothing here reads or writes a file.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

from a2catvn_jax.config import CONFIGS
from a2catvn_jax.errors import UserError

SCALES = ("cpu", "paper")
EVAL_SETS = {"train": "training houses", "new-targets": "new targets", "held-out": "held-out houses"}
BASELINE_LABELS = {"random": "uniformly random policy", "oracle": "shortest-path oracle",
                   "tour": "goal-blind tour of the rooms"}  # the tour: room-type goals only (`env.tour`)
BASELINE_STYLES = {"random": "--", "oracle": "-.", "tour": (0, (1, 1))}  # their lines in the curves

AUX_LOSSES = ("off_policy_critic", "pixel_control", "reward_prediction", "depth", "segmentation", "target_segmentation")
NO_VN = ("train.loss_weights.depth=0", "train.loss_weights.segmentation=0", "train.loss_weights.target_segmentation=0")
NO_RP = "train.loss_weights.reward_prediction=0"
NO_UNREAL = ("train.loss_weights.off_policy_critic=0", "train.loss_weights.pixel_control=0", NO_RP)


def batch(envs: int, rollout: int = 20) -> tuple[str, ...]:
    """Overrides for `envs` environments with `rollout`-step rollouts, logged and
    checkpointed about as often in frames as 16 environments with 20-step rollouts are."""
    per = max(1, envs * rollout // 320)
    steps = () if rollout == 20 else (f"train.rollout_length={rollout}",)
    return (f"env.num_envs={envs}", *steps, f"train.log_every={max(1, 25 // per)}",
            f"train.checkpoint_every={max(10, 500 // per)}")


CLIP_40 = "train.max_grad_norm=40"  # above every gradient norm measured on the house task
# The large-batch candidates of the batch experiment: RMSprop (Table I's) with the
# learning rate scaled by sqrt(B / 16) or B / 16, and the clip at 40. (LAMB with a
# sqrt-scaled rate was tried first and dropped: its steps are a fixed fraction of each
# array's norm, and the policy head, initialised at 0.01, stayed uniform for 90 updates
# at B = 256; docs/results.md, "Larger batches".)
LARGE_BATCH = ("train.lr_scaling=sqrt", CLIP_40)
LARGE_BATCH_LINEAR = ("train.lr_scaling=linear", CLIP_40)
# ... the linear scaling with a warm-up over the first 500k frames (RMSprop's running mean
# of squared gradients starts at 0, so its first steps are about ten times the rate).
LARGE_BATCH_WARMUP = ("train.lr_scaling=linear", "train.lr_warmup_frames=500000", CLIP_40)
# ... and shorter rollouts: B 64 with 5-step rollouts makes as many updates of as many
# frames as B 16 with 20-step ones (Table I's rate); B 256 with 5-step rollouts makes a
# quarter of them, each of four times the frames, at twice the rate (sqrt of the frames).
SHORT_ROLLOUTS_64 = batch(64, rollout=5) + (CLIP_40,)
SHORT_ROLLOUTS_256 = batch(256, rollout=5) + ("train.learning_rate=0.0014", CLIP_40)
# ... and several gradient steps per rollout (train.minibatches): B 256 with 5-step
# rollouts in 4 steps of 64 environments each makes as many steps of as many frames as
# B 64 above (and B 16), at Table I's rate; steps 2-4 learn from a policy 1-3 steps old.
MINIBATCHES_256 = batch(256, rollout=5) + ("train.minibatches=4", CLIP_40)
# ... and the same 4 steps at B 64 with 20-step rollouts (16 environments each): as many
# steps of as many frames as B 16 with the clip at 40, steps 2-4 on a policy 1-3 steps
# old, as at B 256. What it loses against B 16 is what the older policy costs.
MINIBATCHES_64 = batch(64) + ("train.minibatches=4", CLIP_40)
BLIND = ("agent.blind=true",)  # agent.blind=both
# configs/presets/navigation.yaml over house_rooms: what navigates unseen houses best of
# the levers measured (docs/results.md, experiments navigation and navigation_preset).
NAVIGATION = (CLIP_40, "env.scene.num_scenes=256")
# The loss and replay settings of the authors' published code where they differ from the
# defaults (docs/method.md), and their network (configs/presets/authors_network.yaml; its
# convolutions padded, which the 32 px CPU tasks need).
AUTHORS_LOSSES = ("train.loss_weights.critic=1.0", "train.loss_weights.off_policy_critic=2.0",
                  "train.loss_weights.pixel_control=0.1", "train.reward_prediction_loss=sigmoid",
                  "train.reward_prediction_zero_fraction=0.3333", "train.reward_prediction_target=next_frame",
                  "train.pixel_control_reward=rgb", "train.replay_warmup=true", "train.timeout_bootstrap=false")
AUTHORS_NETWORK = ("agent.conv_channels=[32,32,64,32]", "agent.conv_kernels=[7,4,4,1]", "agent.conv_strides=[4,2,2,1]",
                   "agent.conv_padding=same", "agent.dense_size=512", "agent.core_size=512",
                   "agent.vision_heads=transposed", "agent.init=uniform_fan_in")


class ExperimentError(UserError, RuntimeError):
    """An experiment cannot run as asked."""


@dataclasses.dataclass(frozen=True)
class Variant:
    label: str
    overrides: tuple[str, ...] = ()
    pretrain: bool = False  # start from `python -m a2catvn_jax.pretrain` with the same configuration and seed


# Every experiment's control: the configured agent trained on images of zeros, so what it
# reaches needs no sight. Runs are named by their configuration, so the experiments on
# one task share its blind runs.
BLIND_CONTROL = Variant("blind A2CAT-VN", BLIND)


@dataclasses.dataclass(frozen=True)
class Experiment:
    name: str
    title: str
    config: str  # configs/<config>.yaml (paper) and configs/<config>_cpu.yaml (cpu)
    variants: tuple[Variant, ...]
    threshold: float = 0.9  # training success rate for "frames to threshold" at paper scale
    cpu_threshold: float = 0.5  # the same at CPU scale (short runs reach lower rates)
    evaluations: tuple[str, ...] = ("train", "new-targets", "held-out")
    paper: str = ""  # what the paper reports for this comparison
    cpu_only: bool = False  # one configuration, configs/<config>.yaml, a CPU task at both scales
    held_out_points: int = 0  # evaluations in held-out houses during each run (train.eval), evenly spaced; 0: none
    setting: tuple[str, ...] = ()  # overrides of the configuration that every variant and baseline shares (the task)

    def threshold_at(self, scale: str) -> float:
        return self.cpu_threshold if scale == "cpu" else self.threshold

    def config_path(self, scale: str) -> Path:
        if scale not in SCALES:
            raise ExperimentError(f"scale must be one of {SCALES}, got {scale!r}")
        cpu = scale == "cpu" and not self.cpu_only
        return CONFIGS / (f"{self.config}_cpu.yaml" if cpu else f"{self.config}.yaml")


EXPERIMENTS = {e.name: e for e in (
    Experiment(
        "sight", "A2CAT-VN vs the same agent blind on the quickstart task", "quickstart",
        (Variant("A2CAT-VN"), BLIND_CONTROL),
        cpu_threshold=0.7, evaluations=("train",), cpu_only=True,
        paper="Not in the paper. The blind agent's network sees zero images: what it reaches needs no sight, "
              "so the gap between the two is what the images are used for.",
    ),
    Experiment(
        "aux", "A2CAT-VN vs A2C+UNREAL vs A2C, and a blind A2CAT-VN", "image_goals",
        (Variant("A2CAT-VN (pre-trained)", pretrain=True), Variant("A2CAT-VN"), Variant("A2C+UNREAL", NO_VN),
         Variant("A2C", NO_VN + NO_UNREAL), BLIND_CONTROL),
        paper="House3D, 16 houses: average episode length 200 after about 3M frames with the visual-navigation "
              "auxiliary tasks, about 8M without them (A2C+UNREAL); plain A2C is not shown. The blind agent (its "
              "network sees zero images) is a control: what it reaches needs no sight.",
    ),
    Experiment(
        "aux_quickstart", "A2CAT-VN vs A2C+UNREAL vs A2C on the quickstart task", "quickstart",
        (Variant("A2CAT-VN (pre-trained)", ("pretrain.dataset_size=4000", "pretrain.epochs=10"), pretrain=True),
         Variant("A2CAT-VN"), Variant("A2C+UNREAL", NO_VN), Variant("A2C", NO_VN + NO_UNREAL), BLIND_CONTROL),
        cpu_threshold=0.7, evaluations=("train",), cpu_only=True,
        paper="House3D, 16 houses: average episode length 200 after about 3M frames with the visual-navigation "
              "auxiliary tasks, about 8M without them (A2C+UNREAL); plain A2C is not shown. The A2CAT-VN runs are "
              "the sight experiment's, whose blind agent is the control for this task.",
    ),
    Experiment(
        "ablations", "A2CAT-VN without one auxiliary loss at a time", "image_goals",
        (Variant("A2CAT-VN"),) + tuple(
            Variant(f"without {loss.replace('_', ' ')}", (f"train.loss_weights.{loss}=0",)) for loss in AUX_LOSSES)
        + (Variant("A2C+UNREAL", NO_VN), BLIND_CONTROL),
        paper="The paper compares A2CAT-VN with A2C+UNREAL (all three visual-navigation losses removed together) "
              "and reports no leave-one-out ablation.",
    ),
    Experiment(
        "aux_without_rp", "with reward prediction off: A2CAT-VN vs A2C+UNREAL vs A2C", "image_goals",
        (Variant("A2CAT-VN without reward prediction", (NO_RP,)),
         Variant("A2C+UNREAL without reward prediction", NO_VN + (NO_RP,)), Variant("A2C", NO_VN + NO_UNREAL),
         BLIND_CONTROL),
        paper="Its House3D comparison (with and without the visual-navigation losses), here with the "
              "reward-prediction loss off in both, the loss whose gradient dominates the shared layers at the "
              "defaults (docs/results.md). Its A2CAT-VN runs are the ablations experiment's 'without reward "
              "prediction', its A2C and blind runs the aux experiment's.",
    ),
    Experiment(
        "ablations_quickstart", "A2CAT-VN without one auxiliary loss at a time, on the quickstart task", "quickstart",
        (Variant("A2CAT-VN"),) + tuple(
            Variant(f"without {loss.replace('_', ' ')}", (f"train.loss_weights.{loss}=0",)) for loss in AUX_LOSSES)
        + (Variant("A2C+UNREAL", NO_VN), BLIND_CONTROL),
        cpu_threshold=0.7, evaluations=("train",), cpu_only=True,
        paper="The paper compares A2CAT-VN with A2C+UNREAL (all three visual-navigation losses removed together) "
              "and reports no leave-one-out ablation. The A2CAT-VN runs are the sight experiment's.",
    ),
    Experiment(
        "authors", "this package's defaults vs the authors' loss settings and network, on the quickstart task",
        "quickstart",
        (Variant("A2CAT-VN"), Variant("A2CAT-VN, the authors' loss settings", AUTHORS_LOSSES),
         Variant("A2CAT-VN, the authors' network", AUTHORS_NETWORK), BLIND_CONTROL),
        cpu_threshold=0.7, evaluations=("train",), cpu_only=True,
        paper="Where the authors' code and this package differ (docs/method.md): their loss and replay settings "
              "(critic 1.0, off-policy critic 2.0, pixel control 0.1, sigmoid reward prediction on a third of "
              "zero-reward windows and the next frame's reward, RGB pixel-control rewards, a filled replay before "
              "the first update, no bootstrap at time-outs) and their network (padded here for 32 px). "
              "The A2CAT-VN runs are the sight experiment's.",
    ),
    Experiment(
        "memory", "LSTM vs frame stack", "maze",
        (Variant("LSTM"), Variant("frame stack", ("agent.memory=frame_stack",)), BLIND_CONTROL),
        cpu_threshold=0.7,
        paper="DeepMind Lab SeekAvoid, UNREAL auxiliary tasks: the LSTM clearly outperforms four stacked frames.",
    ),
    Experiment(
        "pretraining", "with vs without supervised pre-training", "image_goals",
        (Variant("no pre-training"), Variant("pre-trained", pretrain=True), BLIND_CONTROL),
        paper="Pre-training is part of the House3D run (2e4 images, 30 epochs of Adam); the paper reports no "
              "ablation of it and names its effect as future work.",
    ),
    Experiment(
        "curriculum", "with vs without the curriculum", "image_goals",
        (Variant("no curriculum", ("train.curriculum=false",)), Variant("curriculum", ("train.curriculum=true",)),
         BLIND_CONTROL),
        paper="The curriculum (complexity 0.3 to 1.0 between 5M and 10M frames) is part of the House3D run; "
              "the paper reports no ablation of it.",
    ),
    Experiment(
        "generalisation", "room-type goals over many houses (64 at CPU scale, a new one each episode; 16 at paper scale): training vs held-out houses", "house_rooms",
        (Variant("A2CAT-VN"), BLIND_CONTROL),
        paper="The paper leaves generalisation to unseen houses and unseen targets as future work.",
    ),
    Experiment(
        "navigation", "levers for navigating unseen houses (room-type goals over many houses)", "house_rooms",
        (Variant("A2CAT-VN"), Variant("A2CAT-VN, clip 40", (CLIP_40,)),
         Variant("A2CAT-VN without reward prediction", (NO_RP,)),
         Variant("A2CAT-VN, clip 40, 256 houses", NAVIGATION),
         Variant("A2CAT-VN, clip 40, new houses every 200k frames", (CLIP_40, "train.new_houses_every=625")),
         Variant("A2CAT-VN, clip 40, 256 houses, 20M frames", NAVIGATION + ("train.total_frames=20000000",)),
         BLIND_CONTROL),
        held_out_points=5,
        paper="Not in the paper. Each variant changes one setting that learned faster on the house task, or "
              "(256 houses) trains in four times as many houses, or (new houses) in 64 new ones every 625 "
              "updates (200k frames at B 16), 1,600 over 5M frames, or (20M frames) trains the 256-house "
              "variant four times as long (its learning rate decays to zero over the longer run); the A2CAT-VN and "
              "blind runs are the generalisation experiment's.",
    ),
    Experiment(
        "navigation_preset", "the navigation preset against the paper's settings and the controls that separate "
        "finding the goal from recognising it", "house_rooms",
        (Variant("navigation preset", NAVIGATION), Variant("A2CAT-VN"), BLIND_CONTROL,
         Variant("target-blind navigation preset", NAVIGATION + ("agent.blind=target",)),
         Variant("observation-blind navigation preset", NAVIGATION + ("agent.blind=observation",))),
        held_out_points=5,
        paper="Not in the paper. The preset is configs/presets/navigation.yaml (the navigation experiment's "
              "best lever); its runs are that experiment's variant of the same settings. The target-blind "
              "control trains with the preset but a target image of zeros (it sees the house, not which room is "
              "asked for), the observation-blind one with observations of zeros (it sees the goal, not where it "
              "is); the blind agent (both zeroed) and A2CAT-VN are the generalisation experiment's runs, with "
              "Table I's settings.",
    ),
    Experiment(
        "declared_success", "the navigation preset where success must be declared with a stop action "
        "(env.stop_action): recognising the goal, not only passing it", "house_rooms",
        (Variant("navigation preset", NAVIGATION),
         Variant("target-blind navigation preset", NAVIGATION + ("agent.blind=target",)), BLIND_CONTROL),
        held_out_points=5,
        setting=("env.stop_action=true",),
        paper="Not in the paper, whose episodes succeed when the agent looks at the goal's room, whether it "
              "knows it or not. Here the last action stops the episode and only a stop where that criterion "
              "holds succeeds, so a policy that tours the rooms without reading the goal succeeds only by "
              "guessing (the tour stops in the first room it looks into). Both variants, the random policy, "
              "the oracle and the tour run with the stop action; the target-blind control sees the house but "
              "not which room is asked for; the blind control (Table I's settings) neither.",
    ),
    Experiment(
        "clipping", "gradient-norm clipping with the auxiliary losses", "image_goals",
        (Variant("A2CAT-VN, clip 0.5"), Variant("A2CAT-VN, clip 40", (CLIP_40,)),
         Variant("A2C, clip 0.5", NO_VN + NO_UNREAL), BLIND_CONTROL),
        paper="Table I clips the global gradient norm at 0.5. The auxiliary losses add to that norm, so the clip "
              "also shrinks the actor-critic part of the step; the paper does not discuss this.",
    ),
    Experiment(
        "aux_clip40", "with the gradient-norm clip at 40: A2CAT-VN (pre-trained and not) vs A2C+UNREAL vs A2C",
        "image_goals",
        (Variant("A2CAT-VN (pre-trained), clip 40", (CLIP_40,), pretrain=True), Variant("A2CAT-VN, clip 40", (CLIP_40,)),
         Variant("A2C+UNREAL, clip 40", NO_VN + (CLIP_40,)), Variant("A2C", NO_VN + NO_UNREAL), BLIND_CONTROL),
        paper="Its House3D comparison (with and without the visual-navigation losses), here with every loss "
              "kept and the gradient-norm clip at 40, far above the logged gradient norms: at Table I's 0.5 the clip "
              "acts throughout training with reward prediction and slows learning on this task (the clipping "
              "experiment). Its "
              "A2CAT-VN, clip 40 runs are the clipping experiment's, its A2C and blind runs the aux experiment's.",
    ),
    Experiment(
        "aux_every", "the depth and segmentation losses on every rollout frame vs every 4th (train.aux_every)",
        "image_goals",
        (Variant("A2CAT-VN"), Variant("A2CAT-VN, vision losses every 4th frame", ("train.aux_every=4",)), BLIND_CONTROL),
        paper="The paper computes the depth and segmentation losses on every frame. Every 4th frame divides "
              "their memory and time by about 4 (what lets thousands of environments train in memory); this "
              "measures what it costs learning. The A2CAT-VN runs are the aux experiment's.",
    ),
    Experiment(
        "batch", "larger batches: Table I's settings against a large-batch optimiser and a scaled learning rate",
        "image_goals",
        (Variant("B 16"), Variant("B 16, clip 40", (CLIP_40,)),
         Variant("B 64, Table I", batch(64)), Variant("B 256, Table I", batch(256)),
         Variant("B 64, sqrt-scaled lr, clip 40", batch(64) + LARGE_BATCH),
         Variant("B 256, sqrt-scaled lr, clip 40", batch(256) + LARGE_BATCH),
         Variant("B 256, linear-scaled lr, clip 40", batch(256) + LARGE_BATCH_LINEAR),
         Variant("B 256, linear-scaled lr, warm-up, clip 40", batch(256) + LARGE_BATCH_WARMUP),
         Variant("B 64, 5-step rollouts, clip 40", SHORT_ROLLOUTS_64),
         Variant("B 256, 5-step rollouts, 2x lr, clip 40", SHORT_ROLLOUTS_256),
         Variant("B 256, 5-step rollouts, 4 minibatches, clip 40", MINIBATCHES_256),
         Variant("B 64, 4 minibatches of 16, clip 40", MINIBATCHES_64), BLIND_CONTROL),
        evaluations=("train",),
        paper="Table I trains 16 environments. At the same frame budget B environments make 16 / B as many "
              "updates; the large-batch candidates scale the learning rate by sqrt(B / 16) or B / 16 (with "
              "or without a warm-up over 500k frames) and clip at 40, or shorten the rollouts to 5 steps so "
              "that B 64 makes as many updates as B 16, or (B 256) take 4 gradient steps per rollout; "
              "B 64 in 4 steps of 16 environments measures what learning from a policy 1-3 steps old costs "
              "(B 16 with the clip at 40 is the clipping experiment's run).",
    ),
    Experiment(
        "grid", "grid actions on small rooms: A2CAT-VN vs A2C", "grid",
        (Variant("A2CAT-VN"), Variant("A2C", NO_VN + NO_UNREAL), BLIND_CONTROL),
        cpu_threshold=0.7,
        paper="AI2-THOR, four scenes, grid actions: A2CAT-VN finds the optimal solution after about 5e5 frames.",
    ),
)}
