"""One run: ``simulate`` (start, driver, quantities), the consistent start, one-sided constraints and
events in segments, ensembles of variants, the reduced route's run, and the Trajectory it returns."""
