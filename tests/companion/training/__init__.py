"""Tests of companion.training: the models' training, distillation and export."""
