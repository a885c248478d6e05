"""The sim-to-real gap workflow: replay measured episodes in the twin, localise where
they disagree, fit and name the effects the twin lacks, and show the gap shrink.

``diagnose`` runs the whole workflow; ``localize``, ``shooting``, ``identify``,
``inverse``, ``camera``, ``appearance`` and ``report`` are its parts, and
``candidates`` the effects it can name. Import them from their modules.
"""
