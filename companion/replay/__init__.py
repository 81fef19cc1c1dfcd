"""Offline replay: the per-frame pipeline over a recording, a video or a folder of frames, with
machine-readable results (JSON Lines, masks, summary) and the paper's annotated figure."""
