"""What is done with a model and its runs: statics and virtual work, the cross-check against the
reduced route, derivation checks and printed equations, symmetry and Noether charges, least
action, and the work-precision bench. Never imports the scene or the command line."""
