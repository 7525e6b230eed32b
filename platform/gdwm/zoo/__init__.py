"""The model zoo (README: Model zoo): every trained component is an MLflow model, registered per component name
(``gdwm-tokenizer``, ``gdwm-lora``, ``gdwm-vae``, ``gdwm-unet``) with its variant and lineage as version tags.

``refs`` (``zoo:NAME@ALIAS`` / ``zoo:NAME/VERSION`` and the command's arguments) -> ``registry`` (register, resolve,
pin config references, download, tag) -> ``command`` (``gdwm zoo list|show|promote|load``). Importing this
package is cheap: it loads no MLflow.
"""
