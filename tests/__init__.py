"""The tests: one folder per layer of `rr_actors` (docs/explanation/architecture.md, "Tests")."""
