"""OpenSCENARIO 1.x scenarios: a safe reader (`reader`), lane positions on an imported
OpenDRIVE layout (`lanes`), and the player that steps a scenario's entities (`player`).
docs/sim.md "Scenarios" lists the supported elements."""
