"""Backends for agentsdk: each subpackage implements a controller for one kind of robot (sim, CAN bus, mock)."""
