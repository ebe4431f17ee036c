"""The batched path: the controller and MJX physics stepped together, scanned over time and
vmapped over a batch of parameters (``rollout``)."""
