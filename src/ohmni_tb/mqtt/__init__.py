"""Fleets on MQTT: the daemon publishes its robot to a broker and takes commands from it.

``ohmni serve --mqtt mqtt://broker:1883`` runs :class:`MqttBridge` beside the daemon's
server; ``ohmni fleet`` and :class:`ohmni_tb.fleet.Fleet` read every robot the broker
knows. The topics and payloads are :mod:`ohmni_tb.mqtt.payloads`; reaching the broker is
:mod:`ohmni_tb.mqtt.broker`. Needs the mqtt extra (``pip install 'ohmni_tb[mqtt]'``):
``aiomqtt``, on ``paho-mqtt``. docs/fleet.md has the whole picture.
"""

from __future__ import annotations

from ohmni_tb.mqtt.bridge import MqttBridge, default_robot_id
from ohmni_tb.mqtt.broker import Backoff, Broker

__all__ = ["Backoff", "Broker", "MqttBridge", "default_robot_id"]
