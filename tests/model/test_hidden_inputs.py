"""No ground truth leaks into a prediction: for every model and scene, one-step predictions,
all heads' outputs but the likelihood of the truth, rollouts through the learned simulator and
mass posteriors are bit for bit the same when the graph's hidden quantities are replaced by
random values: true masses, relative log-masses on edges, recorded contacts or pair-force
magnitudes, the target, and the types and radii where a model is not given them by design
(``GIVEN`` says which model reads what, and why, and each model's own ``given`` says the same).

The models are built from the real configs (scene defaults of ``conf/dataset_model/``
included), small, with every parameter perturbed from its initialisation so that no layer
(e.g. a gate initialised to zero) hides an input; they run on the small real datasets.
"""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch

from bgn.graph import Graph, collate
from bgn.model.base import ModelOutput, PhysicsModel
from bgn.rollout import particles, simulator, true_positions
from bgn.simulator import Particles
from bgn.training.run import build_module, plain_stats
from tests.conftest import SMALL, compose_config

SCENES = ["spring", "gravity_r1", "gravity_r2", "collisions"]
MODELS = {  # small versions of every model the README trains
    "bgn_decoder": ["model=bgn", "model.dynamics=decoder", "model.hidden=8",
                    "model.decoder_hidden=8", "model.flow_hidden=8", "model.flow_transforms=1"],
    "bgn_newton": ["model=bgn", "model.dynamics=newton", "model.hidden=8",
                   "model.decoder_hidden=8", "model.flow_hidden=8", "model.flow_transforms=1"],
    "newton": ["model=newton", "model.hidden=8"],
    "gns": ["model=gns", "model.latent=8", "model.mlp_hidden=8",
            "model.message_passing_steps=2"],
    "cranmer_gn": ["model=cranmer_gn", "model.hidden=8", "model.message_dim=4",
                   "model.hidden_layers=1"],
    # the baselines given what the structured heads read (node_inputs=[radius, type])
    "gns_given": ["model=gns_given", "model.latent=8", "model.mlp_hidden=8",
                  "model.message_passing_steps=2"],
    "cranmer_gn_given": ["model=cranmer_gn_given", "model.hidden=8", "model.message_dim=4",
                         "model.hidden_layers=1"],
}
HIDDEN = ("mass", "edge_rel_log_mass", "edge_contact", "target", "types", "radius")
# What a model reads by design, per (model, scene): those fields are kept, the rest scrambled.
# (The pair-force head would also read types, its law per pair of types, on a force scene of
# several types; these force scenes have one. BGN and Newton read no types on collisions: they
# are the classifier's target, not an input. The baselines read neither unless given them,
# node_inputs=[radius, type], or oracle=true.)
GIVEN_BASELINE = {
    "radius": "node_inputs: each particle's radius as a node feature (the force scenes' "
              "radii: zeros, read all the same)",
    "types": "node_inputs: the one-hot type as a node feature, on a scene of several types"}
GIVEN = {
    ("bgn_newton", "collisions"): {
        "radius": "the impulse head: impacts at contact distance r_i + r_j, masses a learned "
                  "function of the radius relative to the scene's largest"},
    ("newton", "collisions"): {
        "radius": "the impulse head: impacts at contact distance r_i + r_j, masses a learned "
                  "function of the radius relative to the scene's largest"},
    **{(name, scene): {k: v for k, v in GIVEN_BASELINE.items()
                       if k == "radius" or scene == "collisions"}
       for name in ("gns_given", "cranmer_gn_given") for scene in SCENES},
}
# PhysicsModel.given's names -> the graph's fields
FIELDS = {"radii": "radius", "types": "types", "masses": "mass"}
# What a rollout is given by the scene: the radius graph (r_i + r_j + margin) is built from
# the radii on collisions, for every model.
SCENE_GIVEN = {"collisions": {"radius": "the radius graph's rule"}}
# the likelihood of the true log-mass: a function of the truth by definition, not a prediction
TRUTH_OUTPUTS = ("mass_nll",)
ROLLOUT_STEPS = 3


@pytest.fixture(scope="module")
def scenes(small_datamodules):
    """The small datamodule of every scene (generated once per session)."""
    return {scene: small_datamodules[scene] for scene in SCENES}


def build(scene: str, model: list[str], dm) -> PhysicsModel:
    """The model of overrides ``model`` for a scene's datamodule, in eval mode."""
    cfg = compose_config("train", [f"dataset={scene}", *SMALL[scene], *model,
                                   "figures=false", "val_rollout_steps=0"])
    torch.manual_seed(0)
    module = build_module(cfg, dict(vars(dm.meta)), plain_stats(dm.stats()), dm.history)
    model = module.model
    with torch.no_grad():  # every layer live: a zero-initialised gate could hide an input
        for p in model.parameters():
            p.add_(0.1 * torch.randn_like(p))
    return model.eval()


def given(name: str, scene: str) -> set[str]:
    return set(GIVEN.get((name, scene), {}))


def scrambled(g: Graph, keep: set[str], contact_scene: bool, seed: int = 7,
              n_types: int | None = None) -> Graph:
    """``g`` with every hidden field not in ``keep`` replaced by random values. Types are
    drawn beyond the scene's types as well: a single-type scene's types change, and a model
    that one-hot encodes them fails loudly; with ``n_types``, other types of the scene."""
    gen = torch.Generator().manual_seed(seed)
    n, e = g.pos.shape[0], g.edge_index.shape[1]

    def randn(*shape: int) -> torch.Tensor:
        return torch.randn(*shape, generator=gen, dtype=torch.float64).to(g.pos.dtype)

    contact = ((torch.rand(e, generator=gen) < 0.5).to(g.pos.dtype) if contact_scene
               else torch.exp(3 * randn(e)))
    values = {"mass": torch.exp(2 * randn(n)), "edge_rel_log_mass": 3 * randn(e),
              "edge_contact": contact, "target": 10 * randn(*g.target.shape),
              "types": (torch.randint(0, 3, (n,), generator=gen) + g.types + 1
                        if n_types is None else (g.types + 1) % n_types),
              "radius": g.radius * torch.exp(randn(n)) + 0.01}
    out = replace(g, **{k: v for k, v in values.items() if k not in keep})
    for k in HIDDEN:  # every scrambled field really changed
        assert k in keep or not torch.equal(getattr(out, k), getattr(g, k)), k
    return out


def frames(dm) -> Graph:
    """Four test frames spread over the split, as one batch."""
    ds = dm.datasets["test"]
    return collate([ds[i] for i in torch.linspace(0, len(ds) - 1, 4).long().tolist()])


def assert_same(a: torch.Tensor | None, b: torch.Tensor | None, what: str) -> None:
    assert (a is None) == (b is None), what
    if a is not None:
        torch.testing.assert_close(a, b, rtol=0, atol=0, equal_nan=True, msg=what)


CASES = [pytest.param(scene, name, id=f"{name}-{scene}") for scene in SCENES for name in MODELS]


@pytest.mark.parametrize(("scene", "name"), CASES)
def test_predictions_ignore_hidden_quantities(scenes, scene: str, name: str) -> None:
    """``predict`` and every head's output (the truth's likelihood aside) on real frames."""
    dm = scenes[scene]
    model = build(scene, MODELS[name], dm)
    g = frames(dm)
    other = scrambled(g, given(name, scene), dm.meta.interaction == "contact")
    with torch.no_grad():
        assert_same(model.predict(g), model.predict(other), "predict")
        out, out_other = model(g), model(other)
    for field in ModelOutput.__dataclass_fields__:
        if field not in TRUTH_OUTPUTS:
            assert_same(getattr(out, field), getattr(out_other, field), field)


def rollouts(model: PhysicsModel, dm, keep: set[str]) -> tuple[torch.Tensor, torch.Tensor]:
    """Positions of rollouts of both test simulations, with the true particles and with their
    masses, types and (unless kept) radii replaced by random values."""
    ds = dm.datasets["test"]
    sims, start = [0, 1], ds.history + 1
    window = torch.as_tensor(true_positions(ds, sims, start - ds.history - 1, start))
    true = particles(ds, sims)
    gen = torch.Generator().manual_seed(3)
    noise = torch.randn(true.masses.shape, generator=gen, dtype=torch.float64)
    other = Particles(
        masses=true.masses * torch.exp(2 * noise).to(true.masses.dtype),
        radii=true.radii if "radius" in keep else true.radii * torch.exp(noise) + 0.01,
        types=(true.types if "types" in keep
               else true.types + 1 + torch.randint(0, 3, true.types.shape, generator=gen)),
        sims=true.sims)
    sim = simulator(model, ds)
    a = sim.rollout(window, true, ROLLOUT_STEPS, start)
    assert not a.failed.any()
    return a.positions, sim.rollout(window, other, ROLLOUT_STEPS, start).positions


@pytest.mark.parametrize(("scene", "name"), CASES)
def test_rollouts_ignore_hidden_quantities(scenes, scene: str, name: str) -> None:
    """Rollouts with the particles' masses (and types, radii where neither the model nor the
    scene's graph reads them) replaced by random values."""
    dm = scenes[scene]
    model = build(scene, MODELS[name], dm)
    keep = given(name, scene) | set(SCENE_GIVEN.get(scene, {}))
    assert_same(*rollouts(model, dm, keep), "rollout positions")


@pytest.mark.parametrize("scene", SCENES)
@pytest.mark.parametrize("name", [n for n in MODELS if n.startswith("bgn")])
def test_mass_posteriors_ignore_hidden_quantities(scenes, scene: str, name: str) -> None:
    """The inverse model's samples, with the same seed, whatever masses the graph carries:
    ``sample_mass`` and the samples of ``mass_posterior`` (whose density at the truth is a
    function of the truth by definition)."""
    dm = scenes[scene]
    model = build(scene, MODELS[name], dm)
    assert model.has_inverse
    g = frames(dm)
    other = scrambled(g, given(name, scene), dm.meta.interaction == "contact")
    results = []
    for graph in (g, other):
        torch.manual_seed(11)
        samples = model.sample_mass(graph, 8)
        torch.manual_seed(11)
        results.append((samples, model.mass_posterior(graph, 8)[0]))
    assert_same(results[0][0], results[1][0], "sample_mass")
    assert_same(results[0][1], results[1][1], "mass_posterior samples")


@pytest.mark.parametrize(("name", "scene", "field"),
                         [(n, s, f) for (n, s), read in GIVEN.items() for f in read])
def test_what_a_model_is_given_is_read(scenes, name: str, scene: str, field: str) -> None:
    """Every entry of ``GIVEN`` is an input: scrambling it alone changes the prediction."""
    dm = scenes[scene]
    model = build(scene, MODELS[name], dm)
    g = frames(dm)
    other = scrambled(g, set(HIDDEN) - {field}, dm.meta.interaction == "contact",
                      n_types=dm.meta.n_types)  # types the model can read
    with torch.no_grad():
        assert not torch.equal(model.predict(g), model.predict(other))


@pytest.mark.parametrize(("scene", "name"), CASES)
def test_a_model_says_what_it_is_given(scenes, scene: str, name: str) -> None:
    """``PhysicsModel.given`` (what the tables print) is ``GIVEN``: what the tests above keep
    and find read; the baselines given radii and types say so in their label."""
    dm = scenes[scene]
    model = build(scene, MODELS[name], dm)
    assert {FIELDS[k] for k in model.given} == given(name, scene)
    if name.endswith("_given"):
        assert model.label.endswith(" + " + "/".join(model.given)), model.label


def test_the_check_can_fail(scenes) -> None:
    """The same comparisons see an input that is read: the GNS oracle, whose node inputs
    include the true log-mass, changes its prediction and its rollout with the masses."""
    dm = scenes["spring"]
    model = build("spring", [*MODELS["gns"], "model.oracle=true"], dm)
    g = frames(dm)
    other = scrambled(g, set(), False)
    with torch.no_grad(), pytest.raises(AssertionError):
        assert_same(model.predict(g), model.predict(other), "predict")
    with pytest.raises(AssertionError):
        assert_same(*rollouts(model, dm, set()), "rollout positions")
