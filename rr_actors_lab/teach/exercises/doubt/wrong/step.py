"""A wrong answer a student may write (the tests check that it fails): nothing is in
doubt, the backup is taken as the truth."""


def in_doubt(state: str) -> bool:
    del state
    return False
