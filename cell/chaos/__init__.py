"""Fault campaigns against a running cell (`cell chaos`): cell.chaos.faults, cell.chaos.campaign."""
