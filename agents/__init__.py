"""The agent programs of adnmesh (``python agents/<kind>.py`` or ``python -m agents.<kind>``)."""
