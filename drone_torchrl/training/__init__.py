"""Training: collectors produce batches, the loop learns from them, the run record keeps the books.

- :mod:`.collectors`: where a batch of episodes comes from (TorchRL reference, or the fast path);
- :mod:`.population`: the agents' policies and optimizers (one agent is a population of one);
- :mod:`.run`: the run record, one per agent (CSV, TensorBoard, checkpoints, evaluation schedule),
  and the writer interface it shares with a population run's (:mod:`.population_record`);
- :mod:`.trainer`: the loop, collect -> loss -> optimizer -> record;
- :mod:`.memory`: keeping freed memory for reuse (large populations on CPU);
- :mod:`.jobs`: turning configs (Hydra jobs) into runs: validation, resume and fork rules, grouping.
"""
