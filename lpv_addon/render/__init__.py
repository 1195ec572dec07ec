"""Final-frame rendering outside the viewport: ``frames`` renders a frame range to EXR and
stats.json (the batch CLI and the Render Batch operator), ``compare`` measures the LPV against
Cycles (the Compare with Cycles operator), ``cycles`` renders the Cycles reference passes."""
