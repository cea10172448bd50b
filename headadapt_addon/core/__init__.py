"""The HeadAdapt method on numpy arrays (Chen & Prakash 2007). Never imports bpy."""
