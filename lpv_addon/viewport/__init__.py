"""The live viewport: ``live`` keeps the LPV up to date through the worker process (plain data:
arrays and names), ``handlers`` tells it what changed and drives its refresh timer, ``overlay``
draws it with Blender's ``gpu`` module and owns every GPU resource."""
