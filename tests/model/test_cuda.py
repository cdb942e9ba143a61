"""Every model on a GPU computes what it computes on the CPU (float64, to round-off): outputs,
losses and gradients, through the shared sparse kernels (``bgn.model.message_passing``) and
their hand-written backward. Skipped where no CUDA device is present (CI has none; run them
on a GPU machine with ``python -m pytest tests/model/test_cuda.py``)."""

from __future__ import annotations

import copy
import json

import pytest
import torch

from bgn.model import MODELS, build_model

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")

HISTORY = 3  # the structured force head fits masses to the window: it needs >= 3
BGN = {"name": "bgn", "hidden": 16, "decoder_hidden": 16, "flow_hidden": 8, "flow_transforms": 2}
SMALL = {  # test-sized versions of every model, and BGN with the structured force head
    "bgn": BGN,
    "bgn_newton": {**BGN, "dynamics": "newton"},
    # the structured head's other ways of reading masses, its substeps and a formula law
    "bgn_newton_source": {**BGN, "dynamics": "newton", "mass_law": "source"},
    "bgn_newton_type": {**BGN, "dynamics": "newton", "mass_law": "type"},
    "bgn_newton_coupling": {**BGN, "dynamics": "newton", "mass_law": "coupling"},
    "bgn_newton_substeps": {**BGN, "dynamics": "newton", "substeps": 4},
    "bgn_formula": {**BGN, "dynamics": "newton", "law": "formula", "law_formula": json.dumps(
        [{"types": [a, b], "terms": [{"kind": "shifted", "power": -2.0, "a": 1.0, "c": 0.01}]}
         for a, b in ((0, 0), (0, 1), (1, 1))])},
    # every edge MLP in chunks of 50 edges, recomputed in the backward pass, on both devices
    "bgn_checkpointed": {**BGN, "contact_message": "vector", "edge_chunk": 50,
                         "checkpoint_edges": 0, "checkpoint_edges_gpu": 0},
    "cranmer_gn": {"name": "cranmer_gn", "hidden": 32, "message_dim": 8, "hidden_layers": 2},
    "gns": {"name": "gns", "latent": 16, "mlp_hidden": 16, "mlp_layers": 2,
            "message_passing_steps": 3},
    "newton": {"name": "newton", "hidden": 16},
}
# on contact scenes dynamics=newton is the impulse head, which reads none of these options
PAIRWISE_ONLY = {name for name in SMALL if name.startswith(("bgn_newton_", "bgn_formula"))}
FITTED = {"bgn_newton_coupling"}
assert set(MODELS) <= set(SMALL)
SCENES = [  # interaction, graph kind, n_types, box (walls), particles
    ("pairwise", "full", 1, None, 7),
    ("pairwise", "full", 2, None, 7),      # per-type masses and formulas
    ("contact", "radius", 2, 4.0, 7),
    ("contact", "radius", 2, 12.0, 300),   # enough edges per receiver to exercise the segments
]


def pair(meta, stats, graph, name, interaction, kind, n_types, box, n):
    """(CPU model, GPU copy, CPU graph, GPU graph), float64."""
    if name in PAIRWISE_ONLY and interaction != "pairwise":
        pytest.skip(f"{name} differs from bgn_newton only in its pair-force head")
    torch.manual_seed(1)
    model = build_model(SMALL[name], meta(n, n_types, interaction, kind, box=box), stats(),
                        HISTORY).double()
    g = graph(n, history=HISTORY, kind=kind, n_types=n_types, contact=kind == "radius",
              box=box, seed=4)
    assert g.edge_index.shape[1] > 0
    return model, copy.deepcopy(model).cuda(), g, g.to("cuda")


def outputs(model, g, noise):
    return model(g, noise) if model.name == "bgn" else model(g)


@pytest.mark.parametrize("name", sorted(SMALL))
@pytest.mark.parametrize(("interaction", "kind", "n_types", "box", "n"), SCENES)
def test_gpu_prediction_equals_cpu(meta, stats, graph, name, interaction, kind, n_types, box,
                                   n):
    cpu, gpu, g, g_gpu = pair(meta, stats, graph, name, interaction, kind, n_types, box, n)
    cpu.eval(), gpu.eval()
    with torch.no_grad():
        expected = cpu.predict(g)
        got = gpu.predict(g_gpu)
    assert got.device.type == "cuda"
    # the coupling head solves for each simulation's couplings (Levenberg-Marquardt): the
    # solve carries round-off further than a forward pass
    tol = 1e-7 if name in FITTED else 1e-9
    torch.testing.assert_close(got.cpu(), expected, atol=tol, rtol=tol)


@pytest.mark.parametrize("name", sorted(SMALL))
@pytest.mark.parametrize(("interaction", "kind", "n_types", "box", "n"), SCENES)
def test_gpu_loss_and_gradients_equal_cpu(meta, stats, graph, name, interaction, kind,
                                          n_types, box, n):
    cpu, gpu, g, g_gpu = pair(meta, stats, graph, name, interaction, kind, n_types, box, n)
    noise = torch.randn(n, dtype=torch.float64)
    losses = []
    for model, batch, eps in ((cpu, g, noise), (gpu, g_gpu, noise.cuda())):
        # BGN trains through the flow's sample, drawn from the noise given; the baselines'
        # only training-mode difference is random input noise, which no two devices share
        model.train(model.name == "bgn")
        terms = model.loss_terms(batch, outputs(model, batch, eps))
        loss = model.total_loss(terms)
        loss.backward()
        losses.append((loss.detach().cpu(), {k: v.detach().cpu() for k, v in terms.items()}))
    (loss_cpu, terms_cpu), (loss_gpu, terms_gpu) = losses
    assert torch.isfinite(loss_cpu)
    torch.testing.assert_close(loss_gpu, loss_cpu, atol=1e-9, rtol=1e-9)
    assert terms_gpu.keys() == terms_cpu.keys()
    for (pname, p), q in zip(cpu.named_parameters(), gpu.parameters()):
        assert (p.grad is None) == (q.grad is None), pname
        if p.grad is not None:
            torch.testing.assert_close(q.grad.cpu(), p.grad, atol=1e-8, rtol=1e-7, msg=pname)


def test_force_matching_on_the_gpu_fits_the_table_the_cpu_fits(small_datamodules):
    """law_init=match (``bgn.model.force_matching``) with the model and the frames on the GPU:
    the normal equations built there, the table solved, the MLP fitted to it on the GPU (the
    pair-force candidates of model.dynamics=auto start so on imported data)."""
    from itertools import islice

    from bgn.model import force_matching as fm
    from bgn.training.run import build_module
    from tests.conftest import SMALL as TRAIN_SMALL
    from tests.conftest import compose_config

    dm = small_datamodules["spring"]
    cfg = compose_config("train", ["dataset=spring", *TRAIN_SMALL["spring"],
                                   "model.dynamics=newton", "model.law_init=match"])
    stats = {k: {n: v.tolist() for n, v in e.items()} for k, e in dm.stats().items()}
    train = list(islice(dm.train_dataloader(), 4))
    val = list(islice(dm.val_dataloader(), 2))
    results = {}
    for device in ("cpu", "cuda"):
        torch.manual_seed(0)
        model = build_module(cfg, dict(vars(dm.meta)), stats, dm.history).model.to(device)
        head = fm.matched_head(model)
        assert head is not None
        results[device] = fm.match_forces(head, [g.to(device) for g in train],
                                          [g.to(device) for g in val], known_masses=True)
    cpu, gpu = results["cpu"], results["cuda"]
    assert cpu is not None and gpu is not None and gpu.kept == cpu.kept
    assert gpu.smoothing == cpu.smoothing and gpu.rows == cpu.rows
    # float32 frames summed in another order: the table's errors to round-off
    assert gpu.table_val_error == pytest.approx(cpu.table_val_error, rel=1e-3)
    assert gpu.val_error < 1e-2 * gpu.val_error_before  # the law fitted on the GPU moves
