//! What a radiotherapy team loads besides the displacement fields: the CT at each breathing
//! phase (virtual 4D-CT), the target's motion and internal target volume, and the DICOM
//! objects (CT series, RTSTRUCT, spatial registrations) a planning system and a PACS accept.
