"""Moved to :mod:`torchslam.app.outputs`; this old path works for one release."""

from .._moved import alias_module

alias_module(__name__, "torchslam.app.outputs")
