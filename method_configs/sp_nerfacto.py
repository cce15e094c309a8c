"""sp-nerfacto: nerfacto with SP on the main field's sample positions."""

from sp_plugins.nerfstudio.radiance_configs import nerfacto_method

sp_nerfacto = nerfacto_method(
    "sp-nerfacto",
    description="Nerfacto + stochastic preconditioning of the field's sample positions (proposal networks unperturbed).",
)
