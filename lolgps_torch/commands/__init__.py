"""The commands users run, ``lolgps COMMAND`` (:mod:`~lolgps_torch.commands.lolgps`), and the
set-up of a stream run they share (:mod:`~lolgps_torch.commands.stream`)."""
