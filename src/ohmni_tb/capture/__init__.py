"""Captures of the bus taken by other software: the vendor's tb-node driver.

:mod:`ohmni_tb.capture.tbnode` reads the log the shipped tb-node plugin
(``tbnode_plugin.js``, printed by ``ohmni bus tbnode-plugin``) writes on the robot, sans-IO:
``ohmni bus convert`` turns it into a capture ``ohmni bus monitor --capture`` decodes.
"""

from __future__ import annotations
