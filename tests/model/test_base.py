"""The model contract's description of a model (``PhysicsModel.label``, ``given``,
``physics``): derived from the real configs (scene defaults of ``conf/dataset_model/``
included), never written per table."""

from __future__ import annotations

import pytest
from omegaconf import OmegaConf

from bgn.model import build_model
from bgn.model.base import GIVEN_FIELDS
from tests.conftest import compose_config
from tests.model.conftest import fake_stats, make_meta

PAIR_FORCES = "central pair forces, equal and opposite"
IMPULSES = "impulses along the normal at the time of impact, equal and opposite, in event order"
SCENES = {  # a synthetic record of each kind of scene: (interaction, graph, n_types, box)
    "spring": ("pairwise", "full", 1, None),
    "gravity_r2": ("pairwise", "full", 1, None),
    "collisions": ("contact", "radius", 2, 4.0),
}
# (scene, overrides) -> label, given, what the physics says (a part of it)
CASES = {
    ("spring", "model=bgn", "model.dynamics=decoder"): ("BGN (paper decoder)", (), "none"),
    ("collisions", "model=bgn", "model.dynamics=decoder"): ("BGN (paper decoder)", (), "none"),
    ("collisions", "model=bgn", "model.dynamics=decoder", "model.contact_gap=true"):
        ("BGN (paper decoder)", ("radii",), "none"),
    ("gravity_r2", "model=bgn_decoder"): ("BGN (paper decoder)", (), "none"),
    ("collisions", "model=bgn_decoder"): ("BGN (paper decoder)", (), "none"),
    ("spring", "model=bgn"):  # the scene's default: the pair-force head, inertial masses held
        ("BGN + pair-force head (masses inertial held)", (),
         f"{PAIR_FORCES}; inertial masses"),
    ("spring", "model=bgn", "model.mass_law=source"):
        ("BGN + pair-force head (masses source held)", (),
         f"{PAIR_FORCES}; masses at the source"),
    ("spring", "model=bgn", "model.rollout_masses=window"):
        ("BGN + pair-force head (masses inertial)", (), f"{PAIR_FORCES}; inertial masses"),
    ("gravity_r2", "model=bgn"):
        ("BGN + pair-force head (masses source held)", (),
         "(mass_law=source); in a rollout fitted once, to its first window, and held"),
    ("collisions", "model=bgn"):  # the scene's default: the impulse head
        ("BGN + impulse head (radii)", ("radii",), IMPULSES),
    ("spring", "model=newton"):
        ("Newton pair-force head (masses inertial)", (), "(mass_law=inertial)"),
    ("collisions", "model=newton"): ("Newton impulse head (radii)", ("radii",), IMPULSES),
    ("collisions", "model=gns"): ("GNS", (), "none"),
    ("collisions", "model=gns_given"): ("GNS + radii/types", ("radii", "types"), "none"),
    ("collisions", "model=gns", "model.node_inputs=[radius]"): ("GNS + radii", ("radii",),
                                                                "none"),
    ("spring", "model=gns_given"): ("GNS + radii", ("radii",), "none"),  # one type: no column
    ("collisions", "model=gns", "model.oracle=true"):
        ("GNS + types/masses (oracle)", ("types", "masses"), "none"),
    ("collisions", "model=cranmer_gn"): ("Cranmer GN", (), "none"),
    ("collisions", "model=cranmer_gn_given"):
        ("Cranmer GN + radii/types", ("radii", "types"), "none"),
}


def built(scene: str, overrides: tuple[str, ...]):
    cfg = compose_config("train", [f"dataset={scene}", *overrides])
    interaction, graph, n_types, box = SCENES[scene]
    meta = make_meta(6, n_types, interaction, graph, box=box)
    return build_model(OmegaConf.to_container(cfg.model, resolve=True), meta, fake_stats(),
                       cfg.dataset.history)


@pytest.mark.parametrize(("scene", "overrides"), [(k[0], k[1:]) for k in CASES],
                         ids=[" ".join(k) for k in CASES])
def test_label_given_and_physics_follow_the_config(scene, overrides) -> None:
    label, given, physics = CASES[(scene, *overrides)]
    model = built(scene, overrides)
    assert (model.label, model.given) == (label, given)
    assert set(model.given) <= set(GIVEN_FIELDS)
    if physics == "none":
        assert model.physics == "none"
    else:
        assert physics in model.physics and model.physics != "none"
    assert model.describe() == {"name": model.name, "label": label, "given": list(given),
                                "trained_with": list(model.trained_with),
                                "supervision": model.supervision, "physics": model.physics}


def test_the_pair_force_head_reads_types_on_a_scene_of_several() -> None:
    """Its law is learned per pair of types there: given types, and the label says so."""
    cfg = compose_config("train", ["dataset=spring", "model=bgn", "model.mass_law=source"])
    model = build_model(OmegaConf.to_container(cfg.model, resolve=True),
                        make_meta(6, 3), fake_stats(), cfg.dataset.history)
    assert model.given == ("types",)
    assert model.label == "BGN + pair-force head (types, masses source held)"


@pytest.mark.parametrize("scene", ["spring", "gravity_r1", "gravity_r2", "collisions"])
def test_bgn_decoder_is_the_scene_defaults_with_the_paper_decoder(scene) -> None:
    """model=bgn_decoder (a study's "BGN (paper decoder)" cell): the scene's BGN defaults
    and optimiser, the decoder, and the dynamics loss on (the law-only weights of the
    pair-force head on gravity would leave a decoder untrained)."""
    ours = compose_config("train", [f"dataset={scene}", "model=bgn_decoder"])
    default = compose_config("train", [f"dataset={scene}", "model=bgn"])
    model, reference = (OmegaConf.to_container(c.model) for c in (ours, default))
    assert model["dynamics"] == "decoder" and model["loss_weights"]["dynamics"] == 1.0
    assert model["loss_weights"]["law"] == 0.0
    assert {k for k in model if model[k] != reference[k]} <= {"dynamics", "loss_weights"}
    assert ours.optimizer == default.optimizer
