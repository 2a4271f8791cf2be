"""Simulation: buses with register-level chip models, the sensor error model, truth generators.

Truth (what the field really is) and sensed values (what a chip reports) are kept apart:
truth comes from a :class:`magstack.sim.truth_source.TruthSource`, sensed values from
:class:`magstack.sim.error_model.ErrorModel`, and chip models only quantise and serve registers.
"""
