"""The review server: one viser server per dataset and what its pages share."""
