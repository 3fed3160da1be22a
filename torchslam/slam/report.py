"""Moved to :mod:`torchslam.app.report`; this old path works for one release."""

from .._moved import alias_module

alias_module(__name__, "torchslam.app.report")
