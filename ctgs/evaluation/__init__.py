"""`ctgs eval`'s work: render a run's held-out views (or an exported model's), measure them with ctgs.metrics
(evaluate), and write metrics.json, the per-image CSV and the tables (report)."""
