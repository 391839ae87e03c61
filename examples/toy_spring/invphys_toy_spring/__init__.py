"""A damped mass on a spring: the smallest complete invphys simulator plugin (docs/writing-a-simulator.md)."""
