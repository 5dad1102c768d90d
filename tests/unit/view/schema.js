// The JSON Schema the viewer's tests need: validate() checks a message against the
// schema its channel advertised or against Foxglove's published one (type, const,
// enum, oneOf, required, properties, items, min/max, minItems/maxItems, base64
// content), strict also refusing members the schema does not name; sameFields()
// compares an advertised schema with a published one, field names and types.
// Each returns a list of errors.
'use strict';
function typeOf(x) {
  if (x === null) return 'null';
  if (Array.isArray(x)) return 'array';
  if (typeof x === 'number') return Number.isInteger(x) ? 'integer' : 'number';
  return typeof x;
}
const BASE64 = /^(?:[A-Za-z0-9+/]{4})*(?:[A-Za-z0-9+/]{2}==|[A-Za-z0-9+/]{3}=)?$/;

function validate(schema, x, where = '$', errors = [], strict = false) {
  if (schema.type) {
    const types = [].concat(schema.type), t = typeOf(x);
    if (!types.includes(t) && !(t === 'integer' && types.includes('number'))) {
      errors.push(`${where}: ${t}, expected ${types.join('|')}`);
      return errors;
    }
  }
  if (schema.const !== undefined && x !== schema.const) errors.push(`${where}: ${x} is not ${schema.const}`);
  if (schema.enum && !schema.enum.includes(x)) errors.push(`${where}: ${x} not in ${schema.enum}`);
  if (schema.oneOf) {
    const fits = schema.oneOf.filter((s) => validate(s, x, where, [], strict).length === 0).length;
    if (fits !== 1) errors.push(`${where}: ${JSON.stringify(x)} fits ${fits} of oneOf, not one`);
  }
  if (schema.minimum !== undefined && x < schema.minimum) errors.push(`${where}: ${x} < ${schema.minimum}`);
  if (schema.maximum !== undefined && x > schema.maximum) errors.push(`${where}: ${x} > ${schema.maximum}`);
  if (schema.contentEncoding === 'base64' && typeof x === 'string' && !BASE64.test(x)) errors.push(`${where}: not base64`);
  if (Array.isArray(x)) {
    if (schema.minItems !== undefined && x.length < schema.minItems) errors.push(`${where}: too few items`);
    if (schema.maxItems !== undefined && x.length > schema.maxItems) errors.push(`${where}: too many items`);
    if (schema.items) x.forEach((v, i) => validate(schema.items, v, `${where}[${i}]`, errors, strict));
  } else if (x && typeof x === 'object') {
    for (const k of schema.required || []) if (!(k in x)) errors.push(`${where}: missing ${k}`);
    const props = schema.properties || {};
    for (const [k, s] of Object.entries(props)) if (k in x) validate(s, x[k], `${where}.${k}`, errors, strict);
    if (strict && schema.properties) {
      for (const k of Object.keys(x)) if (!(k in props)) errors.push(`${where}: ${k} is not a field of ${schema.title}`);
    }
  }
  return errors;
}

// The values a schema admits when it lists them (enum, or oneOf of consts); else null.
function listed(s) {
  if (s.enum) return [...s.enum].sort();
  if (s.oneOf && s.oneOf.every((o) => o.const !== undefined)) return s.oneOf.map((o) => o.const).sort();
  return null;
}

// The advertised schema ours against the published one: the same field names with
// the same types and admitted values, everything the published one requires
// required. Where ours names no fields (a bare {"type": "array"}) it says less
// and is not compared deeper.
function sameFields(ours, pub, where = '$', errors = []) {
  const types = (s) => (s.type ? [].concat(s.type).sort().join('|') : null);
  if (types(pub) && types(ours) !== types(pub)) errors.push(`${where}: type ${types(ours)}, published ${types(pub)}`);
  const a = listed(ours), b = listed(pub);
  if (b && JSON.stringify(a) !== JSON.stringify(b)) errors.push(`${where}: values ${a}, published ${b}`);
  if (ours.items && pub.items) sameFields(ours.items, pub.items, `${where}[]`, errors);
  if (ours.properties && pub.properties) {
    for (const k of Object.keys(pub.properties)) {
      if (!(k in ours.properties)) errors.push(`${where}: no field ${k}`);
      else sameFields(ours.properties[k], pub.properties[k], `${where}.${k}`, errors);
    }
    for (const k of Object.keys(ours.properties)) {
      if (!(k in pub.properties)) errors.push(`${where}: field ${k} is not published`);
    }
    for (const k of pub.required || []) {
      if (!(ours.required || []).includes(k)) errors.push(`${where}: ${k} not required`);
    }
  }
  return errors;
}
module.exports = { validate, sameFields };
