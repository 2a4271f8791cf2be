"""Ground analysis: alignment, apply-a-table-to-a-session, real-data importers, reports, and the
sim-to-real gap diagnosis. No hardware here; may import data, firmware and (only the validation
harness and adapters) sim.
"""
