"""Evaluation around the application: pair metrics and video evaluation against ground truth
(`evaluate`), mosaic fidelity against the source photograph (`fidelity`), stage speed
(`bench`) and the image-pair datasets (`datasets`). The runtime stages never import it."""
