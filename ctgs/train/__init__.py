"""Training: the loop (loop/), the strategies (strategies/) and components (components/) it calls through the hooks
of hooks.py with a narrow state, the config and its rules (config/), the routines the strategies run (routines/),
the step's loss and optimiser (step/), the initial model (start/), and the events the loop yields (events.py)."""
