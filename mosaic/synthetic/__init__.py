"""Synthetic data with exact ground truth: retinal videos (`synth`), photograph pairs of a
curved retina (`curved`) and follow-up visits with planted changes (`followup`). Used by the
CLI's `synth`, the evaluation and the tests; the runtime stages never import it."""
