"""The local stack supervisor: Zenoh router in-process, every service as its own OS process."""
