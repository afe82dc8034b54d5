"""The model variants, one spec each: everything the rest of the package
needs to know about a variant, in one place.

The factory builds a variant with the builder its spec names
(``factory.BUILDERS``); training takes its learning rate and loss from here;
the tables take their row names and row order, the reproduction the variants
it trains and ``cpl_keras.graph`` which variants have a camera graph. A new
variant is one new ``Variant`` entry below plus, if no existing builder
fits, its builder in ``factory.BUILDERS``.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Loss:
    """A training loss, as the rest of the package asks about it (so that no
    module compares loss names)."""

    name: str            #: its name in model configs and run records (``LOSS_MODES``)
    per_output: bool     #: Keras's per-output MAE, set at compile (target scaling applies)
    projection: bool     #: the camera projection terms of Eq. 7 (X, Y, Z through the graph)
    adaptive: bool       #: Eq. 9's learned weights alpha_i on those terms (MTL-CPL-A)


#: Every training loss, by name.
LOSSES = {loss.name: loss for loss in (
    Loss("mae", per_output=True, projection=False, adaptive=False),
    Loss("projection-uniform", per_output=False, projection=True, adaptive=False),
    Loss("projection-adaptive", per_output=False, projection=True, adaptive=True),
    Loss("euclidean", per_output=False, projection=False, adaptive=False),
)}
#: Their names.
LOSS_MODES = tuple(LOSSES)


@dataclass(frozen=True)
class Variant:
    """One network of the paper's Table 1."""

    name: str            #: the variant's name on the command lines
    row: str             #: its row in the paper's tables
    table_order: int     #: position of that row among the paper's model rows
    loss: str            #: loss mode as the paper writes it (``LOSS_MODES``)
    released_loss: str   #: loss mode as released
    learning_rate: float  #: Adam's learning rate (the paper's)
    builder: str         #: key of ``factory.BUILDERS`` that makes its outputs
    camera_graph: bool   #: X, Y, Z come out of the Lambda camera graph
    min_image_size: int | None = None  #: its own minimum (None: the backbone's)
    released_gates: bool = False  #: as released, X, Y, Z pass through sigmoid gates
    mtl: bool = True     #: one of the paper's multi-task networks (two towers, 13 outputs)
    slow: bool = False   #: a training step costs many of the MTL variants' (started first)
    description: str = ""

    def loss_mode(self, as_released=False):
        """The name of its loss (as released: the release's)."""
        return self.released_loss if as_released else self.loss

    def training_loss(self, as_released=False):
        """Its ``Loss`` (as released: the release's)."""
        return LOSSES[self.loss_mode(as_released)]


#: The towers a variant can be built with (``backbones``), and the smallest
#: image side each accepts (InceptionV3's own limit is 75). Here, beside the
#: variants, so that the command lines can offer and check them without
#: importing Keras.
BACKBONES = ("inception_v3", "small", "small_resnet")
MIN_IMAGE_SIZE = {"inception_v3": 75, "small": 16, "small_resnet": 16}
#: How the X, Y, Z terms of the camera projection loss reach the heads
#: (``factory.build_model``).
DISENTANGLE = ("exact", "partial")
#: How the camera projection loss measures Eq. 7's point errors: in metres
#: (the paper's), or divided by each pair's ground-truth depth (an ablation;
#: ``losses.projection_terms``).
POINT_ERRORS = ("metres", "relative")
#: The hidden layers' activation of every regression head: ReLU (the
#: release's heads) or a leaky ReLU of slope 0.2 (Keras's) or 0.01 below zero
#: (ablations: a head whose first-layer units are all at zero on a pair puts
#: out one value there and learns nothing more from it,
#: ``layers.regression_head``).
HEAD_ACTIVATIONS = ("relu", "leaky_relu", "leaky_relu_0.01")
#: How many times an ordinary weight's pace the adaptive weights' log alpha_i
#: move (``CalibrationModel.alpha_rate``; here, beside the variants, so that
#: planning and the run records read it without importing Keras). Adam moves every weight by about
#: the learning rate a step, so with rate 1 log alpha_i changes by at most
#: lr x steps an epoch: 0.04 at the CPU scale's 40 steps an epoch (measured:
#: 0.038-0.055 in every epoch of every logged run), too slow to follow
#: Eq. 9's optimum alpha_i = 1 / L_i while L_i falls by orders of magnitude
#: (after 10 epochs alpha_i L_i spanned 0.09-1.26 instead of 1). At rate 10
#: log alpha_i can move 0.4 an epoch at 40 steps, 3 at 315 (8,000 pairs);
#: at the paper's 5,000 steps an epoch rate 1 would already do.
#: ``--alpha-rate 1`` trains Eq. 9 as the paper writes it.
ALPHA_RATE = 10.0

SPECS = (
    Variant("baseline", "MTL-Baseline", 2, "mae", "mae", 1e-3, "direct", False,
            description="two towers, 13 heads regressing all 13 targets (MAE)"),
    Variant("cpl-u", "MTL-CPL-U", 1, "projection-uniform", "mae", 1e-3, "camera_graph", True,
            description="12 heads, X, Y, Z from the camera graph; uniform projection loss"),
    Variant("cpl-a", "MTL-CPL-A", 3, "projection-adaptive", "mae", 1e-3, "camera_graph", True,
            released_gates=True,
            description="CPL-U with adaptive weights (Eq. 9)"),
    Variant("deep-homo", "Deep-Homo", 0, "euclidean", "euclidean", 1.5e-3, "deep_homo", False,
            min_image_size=16, mtl=False, slow=True,
            description="the modified Deep-Homo network (8 convolutions, Euclidean loss)"),
)
REGISTRY = {spec.name: spec for spec in SPECS}
#: Variant names, in the order of the command lines' choices.
VARIANTS = tuple(REGISTRY)
#: The model rows of the paper's tables, in the paper's order.
MODEL_ROWS = tuple(spec.row for spec in sorted(SPECS, key=lambda s: s.table_order))
#: Table row of each variant.
VARIANT_ROWS = {spec.name: spec.row for spec in SPECS}
#: Variants in the order of the paper's table rows (the reproduction trains these).
TABLE_ORDER = tuple(spec.name for spec in sorted(SPECS, key=lambda s: s.table_order))
#: The paper's three multi-task networks, in table order.
MTL_VARIANTS = tuple(name for name in TABLE_ORDER if REGISTRY[name].mtl)
#: Variants whose training step costs many MTL ones (Deep-Homo: 15-18 small_resnet
#: steps); parallel training starts them first.
SLOW_VARIANTS = tuple(spec.name for spec in SPECS if spec.slow)


def get(name):
    """The spec of variant ``name`` (ValueError naming the choices if unknown)."""
    try:
        return REGISTRY[name]
    except (KeyError, TypeError):
        raise ValueError(f"unknown variant {name!r}; choose one of {', '.join(VARIANTS)}") from None
