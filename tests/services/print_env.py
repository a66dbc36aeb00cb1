"""``python -m tests.services.print_env``: prints the supervisor variable it was started with."""
import os

from services.runtime.orphan import PARENT_ENV

print(f"{PARENT_ENV}={os.environ.get(PARENT_ENV, '')}")
