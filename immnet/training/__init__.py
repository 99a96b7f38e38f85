"""The two-stage curriculum (LightningModules) and the ``immnet fit|test`` CLI."""

from immnet.training.module import Stage1Module, Stage2Module

__all__ = ["Stage1Module", "Stage2Module"]
