"""Outputs: positions and zone events delivered to MQTT brokers and webhooks."""
