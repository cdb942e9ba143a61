"""bgn.training.run's verdict on model.law=auto's formula stage."""

from bgn.training.run import law_verdict


def test_law_verdict_names_each_outcome() -> None:
    assert "no formula fits" in law_verdict({"outcome": "no formula fits", "tolerance": 0.02,
                                             "choice": "network"})
    assert "not compared" in law_verdict({"choice": "network", "validation": {}})
    assert "formula law validates better" in law_verdict(
        {"choice": "formula", "validation": {"formula": {}, "network": {}}})
