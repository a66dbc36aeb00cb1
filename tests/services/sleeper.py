"""A stand-in service process for supervision tests: sleeps until signalled."""
import time

time.sleep(120)
