"""``hcdf-trust fleet``: what each MCU reports over MCUmgr (SMP), checked against the signed
release and the description, and updates that land.

SMP answers are unauthenticated, carry no nonce and no device signature: everything here
is a *host-attested* view of what devices say they run, never device attestation. Every
answer is hostile input: bounded frames, bounded CBOR (:mod:`.cbor`), sequence numbers
checked (:mod:`.smp`).
"""
