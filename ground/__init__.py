"""Ground station CLI and flight-log analysis."""
