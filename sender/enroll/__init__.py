"""Enrollment: a person's model (``.fwm``) from a short video of them, built on the camera host.

It runs the sender's own tracker, pose, lift and sampler, so that the templates are what the
sender will see at run time; that is why it lives in ``sender`` (``models`` may not import the
sender). The pipeline, in order (``build.build_model``): track (``sender.tracker``), fit the
generic head and the poses (``fit``), project the neutral texture (``texture``), enroll the
regions' layers and templates (``layers``), save the model and its preview (``build``)."""
