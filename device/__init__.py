"""Camera side: the mcam-link v1 protocol, the SCAMP-5 daemon and a virtual SCAMP-5."""
