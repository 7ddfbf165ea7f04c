"""ballbar.tools"""
