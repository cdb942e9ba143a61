"""The learned pair law as a formula: ``python -m bgn.laws <run folder or checkpoint>
[finetune=true] ...`` (``bgn.laws.__main__``; ``--help`` lists the keys), and the formula
stage of ``model.law=auto`` (``bgn.laws.stage``).

A pair-force head (``bgn.model.newton``: ``model=newton``, or BGN with
``model.dynamics=newton``) learns a scene's interaction as an MLP ``f(r)`` of the pair's
distance (and types): the force on particle i from j is ``f(r_ij) u_ij``, ``u_ij`` the unit
vector from j to i (positive: repulsive). This package reads that law back, one module per
job:

- ``search``: the symbolic search over expression trees that reads a law back
  (``search_law``: the complexity-error front, the choice within a tolerance or "no formula
  fits"), ``same_form`` (sympy: the same form up to constants) and ``expression_spec`` (a
  member as the model's law);
- ``terms``: the relative scale of a law's residuals, and the old term list's fit
  (``fit_formula``, the baseline the search is measured against);
- ``sample``: a head's law on a grid of distances, the data's pair distances, the scale;
- ``compare``: the law read back by the search (``read_law`` -> ``LawReport``) against the
  true law;
- ``report``: report.md, law.csv, law.json and law.png, the evaluation report's section;
- ``finetune``: the search's front members fitted to the frames as the model's law, the
  best scored on validation rollouts against the network law (``law_choice``); none where
  no formula fits;
- ``stage``: both in a run's ``laws/`` folder (``formula_stage``) and ``model.law=auto``'s
  stage (``law_stage``);
- ``options``: every setting above, typed (``LawOptions``).

The package sits at the evaluation layer (docs/design.md#layers): it reads checkpoints and
rolls out; no module of ``bgn.model`` imports it.
"""
