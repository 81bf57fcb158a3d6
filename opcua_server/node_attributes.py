"""The attributes of a read-only data variable, as the server adds it (AddNodes)."""

from __future__ import annotations

from asyncua import ua


def read_only_variable(name: str, description: str, value, vtype: ua.VariantType,
                       dims: int | None = None) -> ua.VariableAttributes:
    """Display name, description, data type, value, value rank and array dimensions
    (``dims`` elements, or a scalar) of a variable clients may read and not write
    (a writable one gets its access level from the server's write rules)."""
    attrs = ua.VariableAttributes()
    attrs.DisplayName = ua.LocalizedText(name)
    attrs.Description = ua.LocalizedText(description)
    attrs.DataType = ua.NodeId(getattr(ua.ObjectIds, vtype.name))
    attrs.Value = ua.Variant(value, vtype)
    attrs.ValueRank = ua.ValueRank.Scalar if dims is None else ua.ValueRank.OneDimension
    attrs.ArrayDimensions = None if dims is None else [int(dims)]
    attrs.AccessLevel = attrs.UserAccessLevel = ua.AccessLevel.CurrentRead.mask
    return attrs
