"""Moved to :mod:`torchslam.systems.monitor`; this old path works for one release."""

from .._moved import alias_module

alias_module(__name__, "torchslam.systems.monitor")
