"""Trained policies as objects.

- ``policy``: one policy for Python (``lcrl.load(path).act(obs, text)``).
- ``loading``: load any saved policy: one run, an ensemble or a router.
- ``composite``: checkpoint folders made of others, written whole or not at all.
- ``ensemble``: the mean of policies trained apart (``lcrl ensemble``).
- ``route``: experts routed by instruction family (``lcrl route``).
"""
