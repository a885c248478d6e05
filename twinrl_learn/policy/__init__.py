"""The policy: camera images + language instruction + proprio -> an action (chunk).

Two variants share one head and one checkpoint format:

- ``vla``: a small CNN per camera (``front``, ``wrist``) trained from scratch, its
  feature maps FiLM-conditioned on the instruction's sentence embedding
  (all-MiniLM-L6-v2), fused with the proprio state. Where the training data hold the
  object poses (the twin's demos always do), an auxiliary head learns to say where each
  object is relative to the TCP from the same features (``locate_weight``): from 30-120
  demonstrations at 64 px a locating head placed the banana 1.2-1.8 cm off while the
  gripper approached it, which is a missed grasp;
- ``state`` (**privileged**): proprio + ``observation.environment_state`` (object poses
  known only in the twin and the plant), for fast experiments. Its ``inputs`` are either
  ``absolute`` (joint angles, TCP pose, gripper, the objects' poses in the base frame and
  their offsets from the TCP) or ``relative`` (TCP pose and gripper, and each object's
  offset from the TCP and orientation relative to the tool, nothing absolute about the
  objects): the same reach looks the same anywhere on the table, which makes a policy
  learnt from few demonstrations generalise more evenly.

The head is a tanh-squashed Gaussian over normalised actions in [-1, 1]: its
log-likelihood is the imitation loss now and the same network serves as the actor of
the Q-guided objective later. Actions are normalised with the dataset's min/max, states
with its mean/std.

Acting (:meth:`Policy.act`) runs a chunk policy one observation at a time: temporal
ensembling of its predictions (a chunk run open-loop cannot correct itself, and the
grasps it missed were off by a couple of centimetres or tens of degrees), and with
``grasp_hold`` the arm waits while the gripper closes, as a blocking grasp call does on
a real gripper (the grasps a policy lost were lifted while the fingers were still
3-6 cm apart); with ``binary_gripper`` the gripper is commanded open or closed, as the
demonstrations command it (an ensembled value in between half-closed the fingers on the
way down); with ``close_as_demonstrated`` a close waits until the tool is as low over the
object it perceives as the demonstrations close (:mod:`.close_height`: the image policy's
failed grasps closed a centimetre high).

The package, one role per module: :mod:`.config` (``PolicyConfig``), :mod:`.networks`
(the image encoder), :mod:`.inputs` (observations to normalised batches),
:mod:`.normalization`, :mod:`.augmentation`, :mod:`.acting`, :mod:`.close_height`,
:mod:`.checkpoint` (the folder a policy is saved to, which runs no code when loaded) and
:mod:`.model` (``Policy``: networks, action distribution and losses, and the interface
learners and runners use).
"""

from twinrl_learn.policy.checkpoint import is_checkpoint as is_checkpoint
from twinrl_learn.policy.config import IMAGE_SHIFT as IMAGE_SHIFT
from twinrl_learn.policy.config import KINDS as KINDS
from twinrl_learn.policy.config import STATE_NOISE as STATE_NOISE
from twinrl_learn.policy.config import PolicyConfig as PolicyConfig
from twinrl_learn.policy.inputs import quat_matrix as quat_matrix
from twinrl_learn.policy.model import Policy as Policy
from twinrl_learn.policy.networks import FiLMConvEncoder as FiLMConvEncoder
