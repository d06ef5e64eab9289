"""Studies (docs/studies.md): record/replay of Newton systems and the solver
comparison (``systems``, ``compare``), speed versus accuracy (``tradeoff``, ``measures``),
stability at the extremes (``extremes``), and their outputs (``report``)."""
