// The subset of JSON Schema the viewer's advertised schemas use (type, required,
// properties, items, enum, min/max, minItems/maxItems): enough to check each
// message against the schema its channel published. Returns a list of errors.
'use strict';
function typeOf(x) {
  if (x === null) return 'null';
  if (Array.isArray(x)) return 'array';
  if (typeof x === 'number') return Number.isInteger(x) ? 'integer' : 'number';
  return typeof x;
}
function validate(schema, x, where = '$', errors = []) {
  if (schema.type) {
    const types = [].concat(schema.type), t = typeOf(x);
    if (!types.includes(t) && !(t === 'integer' && types.includes('number'))) {
      errors.push(`${where}: ${t}, expected ${types.join('|')}`);
      return errors;
    }
  }
  if (schema.enum && !schema.enum.includes(x)) errors.push(`${where}: ${x} not in ${schema.enum}`);
  if (schema.minimum !== undefined && x < schema.minimum) errors.push(`${where}: ${x} < ${schema.minimum}`);
  if (schema.maximum !== undefined && x > schema.maximum) errors.push(`${where}: ${x} > ${schema.maximum}`);
  if (Array.isArray(x)) {
    if (schema.minItems !== undefined && x.length < schema.minItems) errors.push(`${where}: too few items`);
    if (schema.maxItems !== undefined && x.length > schema.maxItems) errors.push(`${where}: too many items`);
    if (schema.items) x.forEach((v, i) => validate(schema.items, v, `${where}[${i}]`, errors));
  } else if (x && typeof x === 'object') {
    for (const k of schema.required || []) if (!(k in x)) errors.push(`${where}: missing ${k}`);
    for (const [k, s] of Object.entries(schema.properties || {})) if (k in x) validate(s, x[k], `${where}.${k}`, errors);
  }
  return errors;
}
module.exports = { validate };
