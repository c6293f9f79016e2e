"""The workflow: collection (Algorithm 1), run settings, stages, the pipeline, rounds, time budgets, plots."""
