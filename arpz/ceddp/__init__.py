"""The CEDDP server: Zenoh router, cache control, planner, optimisers, Rerun dashboard."""
