"""Helpers the tests share (imported as `tests.support.<module>`); fixtures live in the
`conftest.py` of the folder that uses them (`tests/conftest.py` for every folder)."""
