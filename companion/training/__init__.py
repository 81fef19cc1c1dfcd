"""Training the shipped density network (torch is imported only inside this package).

Retrain the shipped model from scratch (about 35 minutes on 2 CPU threads)::

    python -m companion.training.train --shared ../shared --out companion/models/slz-density.onnx
"""
