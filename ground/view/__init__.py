"""The web view: a run directory's records on a map, live while an experiment runs or replayed after a flight."""
