"""Identifying a DER's dynamics from its measured responses (``adnmesh identify``)."""
