"""jaxedit_lab: the studies built on the jaxedit library, above it and never imported by it.

- :mod:`.simulated` (+ :mod:`.simulated_targets`): the simulated editor, the offline test
  instrument whose targets are known exactly;
- :mod:`.outcome_class`: the outcome measure of a divergent instruction's edits;
- :mod:`.ablation`: the ablation controls (ND, ND-k, the equal-budget controls, IN2N) and the
  pre-registered mechanism study, plugged into the method through its public seams;
- :mod:`.train_editor`: the training of the bundled small InstructPix2Pix (its dataset,
  networks, diffusers writer and quality measures); the trained weights ship in
  :mod:`jaxedit.editors`, where users load them.

The layers and their seams: docs/architecture.md.
"""
