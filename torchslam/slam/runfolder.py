"""Moved to :mod:`torchslam.app.runfolder`; this old path works for one release."""

from .._moved import alias_module

alias_module(__name__, "torchslam.app.runfolder")
