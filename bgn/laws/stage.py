"""The formula stage: a checkpoint's law read back, reported and (``finetune``) fitted to the
frames as the model's law in one folder (``formula_stage``, which ``python -m bgn.laws``
and the ``reproduce`` preset's laws study run), and ``model.law=auto``'s stage inside
``python -m bgn.train`` (``law_stage``), handed to ``bgn.training.run.train``.
"""

from __future__ import annotations

import copy
import json
import logging
from pathlib import Path
from typing import Any

from bgn.laws.compare import read_law
from bgn.laws.finetune import finetune_formula
from bgn.laws.options import DEFAULTS, LawOptions
from bgn.laws.report import finetune_markdown, law_figure, write_report
from bgn.training.budget import Deadline

log = logging.getLogger("bgn.train")


def formula_stage(checkpoint: Path, train_split: Any, val: Any, config: Any,
                  out_dir: Path, finetune: bool = True, options: LawOptions = DEFAULTS,
                  max_seconds: float | None = None, deadline: Deadline | None = None,
                  ) -> dict[str, Any]:
    """The law of ``checkpoint`` read back over ``train_split`` (``read_law``: the law search,
    ``options.search`` within ``options.tolerance``) and written to ``out_dir`` (report.md,
    law.csv, law.json, law.png); with ``finetune`` the formula also fine-tuned as the law and
    scored against the network law on ``val``'s rollouts (``finetune_formula``, from the
    search's front: at most ``options.finetune_members`` members): ``formula.ckpt`` with its
    ``train_config.yaml`` (``config``, the run's, with the formula model's options) and a
    section of report.md. Where no formula fits, nothing is fine-tuned: the network law is
    kept and the section says so. ``options``: the search's and the fine-tuning's
    (``finetune_<key>``); ``max_seconds`` and ``deadline`` stop the fine-tuning early
    (``finetune_formula``). Returns the fine-tuning record (``{}`` without ``finetune``) with
    ``report`` (report.md's path)."""
    from omegaconf import OmegaConf, open_dict

    from bgn.training.checkpoints import read, write_atomic
    from bgn.training.module import load_model

    report = read_law(load_model(checkpoint), train_split, options)
    path = write_report(report, out_dir, title=f"Learned law of {checkpoint}")
    if not finetune:
        return {"report": str(path)}
    record = finetune_formula(checkpoint, train_split, val, report,
                              steps=options.finetune_steps,
                              substeps=options.finetune_substeps,
                              batch_size=options.finetune_batch_size,
                              horizon=options.finetune_horizon,
                              val_sims=options.finetune_val_sims, out_dir=out_dir,
                              max_seconds=max_seconds, deadline=deadline,
                              members=options.finetune_members,
                              val_rollouts=options.finetune_val_rollouts)
    section = finetune_markdown(record)
    print(section)
    write_atomic(path, path.read_text() + "\n" + section)
    if record.get("outcome") == "no formula fits":  # no formula model: nothing more to write
        return {**record, "report": str(path)}
    from bgn.figures import save

    tmp = Path(out_dir) / "law.tmp.png"  # the figure again, with the formula fitted to frames
    save(law_figure(report, json.dumps(record["tuned"])), tmp)
    tmp.replace(Path(out_dir) / "law.png")
    # the run's config with the formula model's options beside formula.ckpt: bgn.evaluate
    # takes the folder of a checkpoint outside checkpoints/ for its run
    tuned_cfg = copy.deepcopy(config)
    hp = read(record["path"])["hyper_parameters"]["model_config"]
    with open_dict(tuned_cfg):
        for key in ("law", "law_formula", "law_scale", "substeps"):
            tuned_cfg.model[key] = hp[key]
    write_atomic(Path(out_dir) / "train_config.yaml", OmegaConf.to_yaml(tuned_cfg))
    return {**record, "report": str(path)}


def law_stage(cfg: Any, best: Path, datamodule: Any, output_dir: Path,
              world_size: int, deadline: Deadline | None = None) -> dict[str, Any]:
    """``model.law=auto``'s stage (``bgn.training.run.train``'s ``law_stage``): the best
    checkpoint's network law read back as a formula, the formula fine-tuned as the law and
    kept where it validates better on rollouts (``formula_stage``, in ``<run>/laws/``; the
    network law where the job's wall-clock cap stopped the comparison); run
    before the test, on the training and validation splits only. Returns its record
    (``choice``: network or formula; ``path``: formula.ckpt). Bounded by its evaluation
    count (``LawOptions.finetune_steps`` per form), so the same run fits the same formula on
    any machine; ``deadline`` (the job's wall-clock cap) stops it earlier, and its record's
    ``budget`` says so (docs/design.md#budgets). Where no formula fits the learned law and no
    member fitted to the frames explains them as well as the network law (``finetune_formula``'s
    frames check), the network law is kept (the record's ``outcome``)."""
    from bgn.training.run import law_verdict  # what the closing summary says of it too

    if world_size > 1:  # one process would tune while the others wait at the test's barrier
        log.info("model.law=auto: the formula stage runs in a single process; run python -m "
                 f"bgn.laws {best} finetune=true after this DDP run")
        return {}
    log.info("model.law=auto: reading the learned law back as a formula and fine-tuning it")
    record = formula_stage(best, datamodule.datasets["train"], datamodule.datasets["val"],
                           cfg, output_dir / "laws", options=DEFAULTS, deadline=deadline)
    log.info(f"model.law=auto: {law_verdict(record)} (report: {record['report']})")
    return record


